"""The embedded default dataset: procedural text-annotated motions in the HumanML3D format.

- `table`: the action table, one spec per action (animation, parameters, captions, adherence check);
  the place to add an action;
- `constants`: `FPS` and the standing-pose constants shared by the animation and the checker;
- `animations`: procedural animation of each action on the 22-joint skeleton (`act_*`);
- `actions`: the clips: `PartSpec`, `make_pose`, `make_motion` chain the parts of a clip;
- `body`: the body model: skeleton constants, `Style`, `State`, `Track` and the kinematics;
- `locomotion`: gaits and footstep planning for walk, run, turn and circle;
- `curves`: easing, keyframes, smoothing and noise over time;
- `captions`: paraphrased captions with part-of-speech tokens, mirrored captions;
- `generate`: `generate_dataset(out_dir, num_clips, seed)` writes the dataset;
- `measure`: what the checker measures on joints (facing, heading, speed, flight);
- `adherence`: `check_motion` / `check_dataset`, the prompt-adherence checker.
"""

from mmm.data.synthetic.adherence import AdherenceResult, check_dataset, check_motion, standing_height
from mmm.data.synthetic.generate import generate_dataset

__all__ = ["AdherenceResult", "check_dataset", "check_motion", "standing_height", "generate_dataset"]
