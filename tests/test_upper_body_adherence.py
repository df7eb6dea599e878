"""Upper-body editing on the synthetic dataset, checked by its adherence checker: a part-aware
model trained briefly here gives walking and squatting sources the requested upper-body action
(wave, raise arms, punch) while their lower-body action stays what it was.

The dataset keeps the clips made only of actions of one body part (stand, walk, squat, wave, raise
arms, punch), so that a few minutes of CPU training suffice; the rest of the package trains on
all of it. The fixture trains 1,400 steps (about 4.5 minutes on 2 CPU cores), so the module is
`long`: left out of `make test`, run by `make test-long`."""

import json
import time

import pytest
from mlflow.tracking import MlflowClient

from mmm.generation.sampler import SamplingConfig

KEPT_ACTIONS = {"stand", "walk", "squat", "wave", "raise_arms", "punch"}
# Stage 1 needs about 800 steps before a punch's full reach (0.4 m ahead of the shoulder, the
# checker's threshold) survives reconstruction; at 400 its peak comes back 0.35-0.38 m.
STAGE1_STEPS, STAGE2_STEPS = 800, 600
# Half the default batch: at a slow hour on the 2.6 GHz Xeon the fixture took 214 s alone, against
# 385 s at batch 64 (under cProfile; 507 s inside a whole `make test`). The edits measured below
# came out no worse: upper 0.97 against 0.77, both 0.90 against 0.77, and 0.9 of the sources kept
# through the tokenizer against 1.0. bfloat16 instead was 1.4x faster and kept only 0.7 of them.
BATCH_SIZE = 32

pytestmark = pytest.mark.long


def focused_dataset(root):
    from mmm.data.synthetic.generate import generate_dataset

    generate_dataset(root, num_clips=1000, seed=0, progress=False)
    for split in ("train", "val", "test", "train_val", "all"):
        ids = (root / f"{split}.txt").read_text().split()
        keep = [
            i
            for i in ids
            if {p["action"] for p in json.loads((root / "labels" / f"{i}.json").read_text())["parts"]}
            <= KEPT_ACTIONS
        ]
        (root / f"{split}.txt").write_text("\n".join(keep) + "\n")
    return root


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from mmm.generation.model import TextToMotion
    from mmm.training.configs import load_stage1_config, load_stage2_config
    from mmm.training.stage1 import train_stage1
    from mmm.training.stage2 import train_stage2

    out = tmp_path_factory.mktemp("upper-body")
    root = focused_dataset(out / "data")
    common = [
        f"data.root={root}",
        "data.synthesize=null",
        f"logger.tracking_uri=sqlite:///{out}/mlflow.db",
        f"logger.artifact_root={out}/art",
        "trainer.enable_progress_bar=false",
        f"data.batch_size={BATCH_SIZE}",
    ]
    started = time.perf_counter()
    stage1 = train_stage1(
        load_stage1_config(
            [
                *common,
                f"output_dir={out}/s1",
                "callbacks.preview_clips=0",
                "callbacks.usage_plot=false",
                f"trainer.max_steps={STAGE1_STEPS}",
                f"trainer.val_check_interval={STAGE1_STEPS}",
                "refine.steps=0",  # the thresholds below were set on the tokenizer without refinement
            ],
            parts=True,
        )
    )
    stage1_seconds = time.perf_counter() - started
    stage2 = train_stage2(
        load_stage2_config(
            [
                *common,
                f"stage1={stage1.best_checkpoint}",
                f"output_dir={out}/s2",
                f"token_cache_dir={out}/tokens",
                f"text.cache_dir={out}/text",
                "callbacks.preview_captions=1",
                f"trainer.max_steps={STAGE2_STEPS}",
                f"trainer.val_check_interval={STAGE2_STEPS}",
            ],
            parts=True,
        )
    )
    print(
        f"[upper body] stage1-parts {stage1_seconds:.0f} s, stage2-parts "
        f"{time.perf_counter() - started - stage1_seconds:.0f} s"
    )
    model = TextToMotion.from_files(stage2.best_checkpoint, stage1.best_checkpoint)
    return {
        "model": model,
        "root": root,
        "stage1": stage1,
        "stage2": stage2,
        "uri": f"sqlite:///{out}/mlflow.db",
    }


@pytest.mark.slow
def test_edits_do_the_requested_upper_action_and_keep_the_lower_one(trained):
    from mmm.evaluation.upper_body import upper_body_adherence

    model, root = trained["model"], trained["root"]
    result = upper_body_adherence(model, root, "test", max_sources=10, lower_mask=0.5, seed=0)
    print(f"[upper body] {json.dumps(result)}")
    assert result["edits"] == 3 * result["sources"] >= 15 and {
        k.split(" on ")[1] for k in result["per_action"]
    } == {"walk", "squat"}
    # The lower body is kept: every source whose action survives the tokenizer keeps it after the edit.
    assert result["lower"] >= result["source_reconstructed"] - 0.05 and result["source_reconstructed"] >= 0.8
    # The requested upper-body action is there in most edits, for each of the three actions.
    assert result["upper"] >= 0.6 and result["both"] >= 0.5
    # Punches are the weak case: on walking sources the source's arm swing often wins after this
    # short training (measured on this package's CPU machines at batch 64: 2-4 of 10 punches, none
    # of 8 on walking sources in one run, and 600 or 900 stage-2 steps alike; at batch 32, 9 of
    # 10); each action must appear.
    for action, least in (("wave", 0.3), ("raise_arms", 0.3), ("punch", 0.1)):
        done = sum(result["per_action"].get(f"{action} on {lower}", [0, 0])[0] for lower in ("walk", "squat"))
        total = sum(
            result["per_action"].get(f"{action} on {lower}", [0, 0])[1] for lower in ("walk", "squat")
        )
        assert done / total >= least, (action, done, total)


@pytest.mark.slow
def test_the_lower_body_condition_is_what_limits_the_upper_body(trained):
    """Figure 14: the more lower-body codes are shown (and the weaker the text is pushed), the
    more the upper body follows the legs instead of the text; the checker sees it."""
    from mmm.evaluation.upper_body import upper_body_adherence

    model, root = trained["model"], trained["root"]
    constrained = upper_body_adherence(
        model,
        root,
        "test",
        max_sources=10,
        lower_mask=0.0,
        seed=0,
        sampling=SamplingConfig(guidance_scale=1.0),
    )
    free = upper_body_adherence(
        model,
        root,
        "test",
        max_sources=10,
        lower_mask=1.0,
        seed=0,
        sampling=SamplingConfig(guidance_scale=1.0),
    )
    print(
        f"[upper body] lower shown, no guidance: {constrained['upper']:.2f}; lower hidden: "
        f"{free['upper']:.2f}"
    )
    assert free["upper"] >= constrained["upper"] + 0.2
    assert free["lower"] == pytest.approx(
        constrained["lower"], abs=0.1
    )  # the legs are the source's either way


@pytest.mark.slow
def test_part_aware_runs_log_per_codebook_metrics_and_previews(trained):
    client = MlflowClient(trained["uri"])
    stage1 = client.get_run(trained["stage1"].run_id)
    assert {
        "codebook/lower/perplexity",
        "codebook/upper/perplexity",
        "collapse/upper/window_active_fraction",
    } <= set(stage1.data.metrics)
    assert stage1.data.metrics["val/mpjpe_root_aligned_mm"] < 80
    previews = [f.path for f in client.list_artifacts(trained["stage2"].run_id, "previews")]
    assert previews and previews[0].endswith(".gif")
