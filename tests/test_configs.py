"""Every file of every config group composes into a valid, typed training config."""

import pytest
from omegaconf import OmegaConf

from mmm.config import compose, conf_dir, to_object
from mmm.training.stage1 import Stage1Config, load_stage1_config

GROUPS = sorted(p.name for p in conf_dir().iterdir() if p.is_dir())
STAGE1_OPTIONS = [(g, p.stem) for g in GROUPS for p in sorted((conf_dir() / g).glob("*.yaml")) if not p.stem.startswith("stage2")]


@pytest.mark.parametrize("group, option", STAGE1_OPTIONS)
def test_stage1_composes_with_every_option(group, option):
    cfg = load_stage1_config([f"{group}={option}"])
    chosen = OmegaConf.load(conf_dir() / group / f"{option}.yaml")
    primary = OmegaConf.load(conf_dir() / "train_stage1.yaml").get(group, {})  # set over the group file
    for key, value in chosen.items():
        if not OmegaConf.is_dict(value) and key not in primary:
            assert cfg[group][key] == value, f"{group}.{key}"
    assert isinstance(to_object(cfg), Stage1Config)


def test_defaults_are_the_cpu_demo_and_paper_sizes_differ():
    cfg = to_object(load_stage1_config())
    assert (cfg.data.name, cfg.trainer.accelerator, cfg.optim.lr) == ("synthetic", "cpu", 1e-3)
    assert cfg.model.tokenizer.num_codes == 512
    paper = to_object(load_stage1_config(["model=paper", "optim=stage1_paper", "trainer.max_steps=5"]))
    assert (paper.model.tokenizer.width, paper.model.tokenizer.num_codes, paper.optim.lr, paper.trainer.max_steps) == (512, 8192, 2e-4, 5)


def test_unknown_group_option_lists_the_choices():
    with pytest.raises(ValueError, match="options: cpu, ddp, ddp_cpu, gpu, multinode"):
        compose("train_stage1", ["trainer=tpu"])
