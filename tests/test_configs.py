"""Every file of every config group composes into a valid, typed training config of each stage."""

import re
from dataclasses import fields

import pytest
from omegaconf import OmegaConf

from mmm.config import compose, conf_dir, to_object
from mmm.training.configs import (
    Stage1Config,
    Stage2Config,
    load_evaluator_config,
    load_stage1_config,
    load_stage2_config,
)

STAGES = {
    "train_stage1": (Stage1Config, load_stage1_config),
    "train_stage2": (Stage2Config, load_stage2_config),
}
GROUPS = sorted(p.name for p in conf_dir().iterdir() if p.is_dir())


def cases():
    for entry, (schema, _) in STAGES.items():
        stage = entry.split("_")[1]
        names = {f.name for f in fields(schema)}
        for group in GROUPS:
            if group not in names:
                continue
            for path in sorted((conf_dir() / group).glob("*.yaml")):
                if group in ("optim", "callbacks") and not path.stem.startswith(stage):
                    continue  # each stage has its own optimizer recipes and callbacks
                yield entry, group, path.stem


@pytest.mark.slow
@pytest.mark.parametrize("entry, group, option", list(cases()))
def test_every_option_composes(entry, group, option):
    schema, load = STAGES[entry]
    cfg = load([f"{group}={option}"])
    chosen = OmegaConf.load(conf_dir() / group / f"{option}.yaml")
    primary = OmegaConf.load(conf_dir() / f"{entry}.yaml").get(group, {})  # set over the group file
    for key, value in chosen.items():
        if not OmegaConf.is_dict(value) and key not in primary and key != "extends":
            assert cfg[group][key] == value, f"{group}.{key}"
    assert isinstance(to_object(cfg), schema)


def test_defaults_are_the_cpu_demo_and_paper_sizes_differ():
    cfg = to_object(load_stage1_config())
    assert (cfg.data.name, cfg.trainer.accelerator, cfg.optim.lr) == ("synthetic", "cpu", 1e-3)
    assert cfg.model.tokenizer.num_codes == 512
    paper = to_object(load_stage1_config(["model=paper", "optim=stage1_paper", "trainer.max_steps=5"]))
    assert (
        paper.model.tokenizer.width,
        paper.model.tokenizer.num_codes,
        paper.optim.lr,
        paper.trainer.max_steps,
    ) == (512, 8192, 2e-4, 5)
    s2 = to_object(load_stage2_config(["model=paper", "optim=stage2_paper"]))
    assert (
        s2.model.transformer.embed_dim,
        s2.model.transformer.num_layers,
        s2.optim.betas,
        s2.optim.milestones,
    ) == (1024, 18, [0.5, 0.9], [150000])
    assert s2.text.encoder == "minilm" and s2.stage1 is None

    # The demo's stage 2 trains 1,500 steps from a trainer file of its own, so that another
    # trainer (the paper's 300k on a GPU) brings its own count; the part-aware one keeps 1,000.
    def steps(cfg):
        return cfg.trainer.max_steps, cfg.trainer.val_check_interval

    assert steps(load_stage2_config()) == (1500, 150)
    assert steps(load_stage2_config(["trainer=gpu"])) == (300000, 5000)
    assert steps(load_stage2_config(parts=True)) == steps(load_stage1_config()) == (1000, 100)


def test_unknown_group_option_lists_the_choices():
    with pytest.raises(ValueError, match="options: cpu, cpu_stage2, ddp, ddp_cpu, gpu, multinode"):
        compose("train_stage1", ["trainer=tpu"])
    with pytest.raises(ValueError, match="num_cross_layers=7 must be between 0 and num_layers=6"):
        to_object(
            load_stage2_config(["model.transformer.num_layers=6", "model.transformer.num_cross_layers=7"])
        )


def test_part_aware_configs_extend_the_whole_body_ones():
    base, parts = (
        OmegaConf.to_container(load_stage1_config()),
        OmegaConf.to_container(load_stage1_config(parts=True)),
    )
    assert (
        parts["model"]["tokenizer"]["part_aware"] is True
        and parts["logger"]["experiment"] == "mmm-stage1-parts"
    )
    assert parts["output_dir"] == "outputs/stage1-parts"
    differing = {k for k in base if base[k] != parts[k]}
    # the rest inherited
    assert differing == {"model", "logger", "output_dir", "refine", "loss", "encode", "trainer"}
    assert {k for k in base["trainer"] if base["trainer"][k] != parts["trainer"][k]} == {"precision"}
    assert (base["trainer"]["precision"], parts["trainer"]["precision"]) == ("auto", "32-true")
    assert base["encode"] == {"candidates": 4, "sweeps": 1, "precision": "auto"}
    assert parts["encode"]["candidates"] == 1
    # its tokenizer training as its upper-body figures were measured, the rest of both groups inherited
    assert parts["refine"] == {**base["refine"], "steps": 1000}
    assert parts["loss"] == {**base["loss"], "path_weight": 0.0}
    assert {k: v for k, v in parts["model"]["tokenizer"].items() if k != "part_aware"} == {
        k: v for k, v in base["model"]["tokenizer"].items() if k != "part_aware"
    }
    s2 = to_object(
        load_stage2_config(["model=paper", "corruption.lower_mask=0.5"], parts=True)
    )  # groups and overrides still apply
    assert (
        s2.part_aware,
        s2.stage1_experiment,
        s2.corruption.lower_mask,
        s2.model.transformer.num_layers,
    ) == (True, "mmm-stage1-parts", 0.5, 18)
    assert s2.corruption.cond_drop == 0.1  # from train_stage2.yaml


def test_extends_is_one_level(tmp_path):
    (tmp_path / "a.yaml").write_text("x: 1\ny: 2\n")
    (tmp_path / "b.yaml").write_text("extends: a\ny: 3\n")
    (tmp_path / "c.yaml").write_text("extends: b\n")
    assert OmegaConf.to_container(compose("b", ["x=5"], directory=tmp_path)) == {"x": 5, "y": 3}
    with pytest.raises(ValueError, match="one level only"):
        compose("c", directory=tmp_path)
    # A group's option extends another option of its group the same way.
    (tmp_path / "trainer").mkdir()
    (tmp_path / "trainer" / "base.yaml").write_text("steps: 10\nevery: 5\ndevice: cpu\n")
    (tmp_path / "trainer" / "longer.yaml").write_text("extends: base\nsteps: 20\n")
    (tmp_path / "trainer" / "longest.yaml").write_text("extends: longer\n")
    (tmp_path / "run.yaml").write_text("defaults:\n  - trainer: longer\n")
    run = compose("run", ["trainer.every=4"], directory=tmp_path)
    assert OmegaConf.to_container(run) == {"trainer": {"steps": 20, "every": 4, "device": "cpu"}}
    with pytest.raises(ValueError, match=r"longest.yaml extends trainer/longer.yaml, which extends another"):
        compose("run", ["trainer=longest"], directory=tmp_path)
    # The demo's stage-2 trainer is the CPU one with its own step count.
    cpu, demo = (
        OmegaConf.to_container(compose("train_stage1", [f"trainer={t}"]))["trainer"]
        for t in ("cpu", "cpu_stage2")
    )
    assert {k for k in cpu if cpu[k] != demo[k]} == {"max_steps", "val_check_interval"}


def _flat(cfg, prefix=""):
    out = {}
    for key, value in cfg.items():
        name = f"{prefix}{key}"
        out.update(_flat(value, name + ".") if OmegaConf.is_dict(value) else {name: value})
    return out


def test_recipe_quality_is_the_demo_longer_and_wider_in_folders_of_its_own():
    from mmm.pipeline.configs import load_pipeline_config

    pipeline = load_pipeline_config(["recipe=quality"])
    assert pipeline.state_file == "outputs/quality/pipeline/state.json"
    assert list(pipeline.overrides.stage1) == ["recipe=quality"]
    assert list(pipeline.overrides.stage2) == ["recipe=quality"]
    assert "adherence_max_items" not in str(pipeline.overrides.evaluate)  # every test caption
    # The recipe's evaluator keeps the 400 steps it was measured with; the demo's trains 300.
    assert load_evaluator_config([]).trainer.max_steps == 300
    quality_evaluator = load_evaluator_config(list(pipeline.overrides.evaluator))
    assert (quality_evaluator.trainer.max_steps, quality_evaluator.trainer.val_check_interval) == (400, 200)
    assert quality_evaluator.output_dir == "outputs/quality/evaluator"
    # Every step trains and measures on the larger synthetic set (the default's val and test clips);
    # a dataset named on the command line replaces it whole.
    assert pipeline.data.name == "synthetic_large" and pipeline.data.root == "data/synthetic-large"
    assert pipeline.data.synthesize.extra_train_clips == 4500 and pipeline.data.synthesize.num_clips == 1500
    own = load_pipeline_config(["recipe=quality", "data=humanml3d", "data.root=/data/HumanML3D"]).data
    assert (own.name, own.root, own.synthesize) == ("humanml3d", "/data/HumanML3D", None)

    def changed(load):
        demo, quality = _flat(load([])), _flat(load(["recipe=quality"]))
        large = {
            "data.name": "synthetic_large",
            "data.root": "data/synthetic-large",
            "data.synthesize.extra_train_clips": 4500,
        }
        assert {k: quality.pop(k) for k in large} == large
        assert {k: demo.pop(k) for k in large} == {
            "data.name": "synthetic",
            "data.root": "data/synthetic",
            "data.synthesize.extra_train_clips": 0,
        }
        assert demo.keys() == quality.keys()
        return {k: quality[k] for k in demo if demo[k] != quality[k]}

    assert changed(load_stage1_config) == {
        "output_dir": "outputs/quality/stage1",
        "trainer.max_steps": 3000,
        "trainer.val_check_interval": 500,
    }
    assert changed(load_stage2_config) == {
        "output_dir": "outputs/quality/stage2",
        "stage1_output_dir": "outputs/quality/stage1",
        "model.transformer.embed_dim": 256,
        "model.transformer.num_heads": 8,
        # the code search's codes at 5e-4, as the recipe was measured (the demo: the nearest, 1e-3)
        "token_encoding": "tokenizer",
        "optim.lr": 5e-4,
        "optim.milestones": [4900],  # one drop, as measured (the demo: the last quarter, final_share)
        "optim.final_share": 0.0,
        "trainer.max_steps": 6300,  # its last validation: every step in a checkpoint
        "trainer.val_check_interval": 300,
        "callbacks.adherence_captions": 128,
        "callbacks.checkpoint.monitor": "val_adherence/ordered_rate",
        "callbacks.checkpoint.mode": "max",
    }
    # Both synthetic datasets draw the captions asking for an action more than once twice, however
    # spelled; HumanML3D and KIT as they are.
    oversample = load_stage2_config(["recipe=quality"]).data.oversample
    assert oversample == load_stage2_config([]).data.oversample and oversample.factor == 2
    pattern = re.compile(oversample.pattern, re.IGNORECASE)
    asks_more_than_once = ["a man jumps twice", "she does 3 squats", "Two jumps", "squats three times"]
    other = ["a person jumps once", "one squat", "someone walks slowly", "jumps a single time"]
    assert all(pattern.search(c) for c in asks_more_than_once)
    assert not any(pattern.search(c) for c in other)
    assert load_stage2_config(["data=humanml3d"]).data.oversample.pattern == ""
    # The command line still wins over the recipe.
    given = ["recipe=quality", "trainer.max_steps=7", "trainer.val_check_interval=7"]
    assert load_stage2_config(given).trainer.max_steps == 7
