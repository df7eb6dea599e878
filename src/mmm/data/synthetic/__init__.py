"""The embedded default dataset: procedural text-annotated motions in the HumanML3D format.

- `actions`: procedural animation of each action on the 22-joint skeleton (`make_pose`, `make_motion`);
- `body`: the body model: skeleton constants, `Style`, `State`, `Track` and the kinematics;
- `locomotion`: gaits and footstep planning for walk, run, turn and circle;
- `curves`: easing, keyframes, smoothing and noise over time;
- `captions`: paraphrased captions with part-of-speech tokens, mirrored captions;
- `generate`: `generate_dataset(out_dir, num_clips, seed)` writes the dataset;
- `adherence`: `check_motion` / `check_dataset`, the prompt-adherence checker.
"""

from mmm.data.synthetic.adherence import AdherenceResult, check_dataset, check_motion, standing_height

__all__ = ["AdherenceResult", "check_dataset", "check_motion", "standing_height", "generate_dataset"]


def __getattr__(name):
    # generate imports torch-heavy modules; load it only when asked for.
    if name == "generate_dataset":
        from mmm.data.synthetic.generate import generate_dataset

        return generate_dataset
    raise AttributeError(name)
