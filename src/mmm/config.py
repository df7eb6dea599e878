"""Configs: YAML files in conf/ composed by a defaults list, overridden from the command line.

conf/<name>.yaml may start with a defaults list naming one file per config group, and groups are
folders (conf/data/synthetic.yaml is option `synthetic` of group `data`):

    defaults:
      - data: synthetic
      - trainer: cpu

An option may start with `extends: other` (another option of its group, which extends none) and
change a few of its keys.

Overrides are `group=option` (choose another file of a group) or `dotted.key=value`; the result
is validated against a dataclass schema when one is given, so a misspelt key is an error.

`recipe=NAME` applies conf/recipe/NAME/<config>.yaml (or the file of the config it extends): a
set of settings for one command, with group choices of its own in a defaults list. Precedence,
lowest first: the config's defaults and keys, the recipe's, then the command line's.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, Sequence

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException


class ConfigError(ValueError):
    pass


def check_whole(key: str, value, least: int, note: str = "") -> None:
    """ConfigError `<key>=<value>: must be a whole number of at least <least><note>` unless value is
    an int (not a bool) of at least `least`."""
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ConfigError(f"{key}={value!r}: must be a whole number of at least {least}{note}")


CONF_DIR_VARIABLE = "MMM_CONF_DIR"


def conf_dir() -> Path:
    """The conf/ folder: $MMM_CONF_DIR, else the copy an installed package carries (mmm/conf, which
    setup.py puts in the wheel), else the checkout's (beside src/), else ./conf."""
    if os.environ.get(CONF_DIR_VARIABLE):
        return Path(os.environ[CONF_DIR_VARIABLE])
    here = Path(__file__).resolve().parent
    # Installed first: an installed package's parents are site-packages, where `conf` can be anything.
    for candidate in (here / "conf", here.parents[1] / "conf"):
        if candidate.is_dir():
            return candidate
    return Path.cwd() / "conf"


def _load_yaml(path: Path) -> DictConfig:
    try:
        cfg = OmegaConf.load(path)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except Exception as e:  # YAML syntax errors
        raise ConfigError(f"{path}: cannot parse ({e})") from None
    if not isinstance(cfg, DictConfig):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return cfg


def _load_option(directory: Path, group: str, option: str) -> DictConfig:
    """conf/<group>/<option>.yaml, on top of the option it `extends` (one level)."""
    path = directory / group / f"{option}.yaml"
    cfg = _load_yaml(path)
    base_name = cfg.pop("extends", None)
    if base_name is None:
        return cfg
    base = _load_yaml(directory / group / f"{base_name}.yaml")
    if "extends" in base:
        raise ConfigError(f"{path} extends {group}/{base_name}.yaml, which extends another: one level only")
    return OmegaConf.merge(base, cfg)


def _options(directory: Path, group: str) -> list[str]:
    return sorted(p.stem for p in (directory / group).glob("*.yaml"))


RECIPE = "recipe"


def _choices(defaults, where: Path) -> dict[str, str]:
    """{group: option} of a defaults list."""
    choices: dict[str, str] = {}
    for entry in defaults:
        if not isinstance(entry, DictConfig) or len(entry) != 1:
            raise ConfigError(f"{where}: each defaults entry must be one 'group: option', got {entry}")
        ((group, option),) = entry.items()
        choices[str(group)] = str(option)
    return choices


def _recipe(directory: Path, recipe: str, names: list[str]) -> DictConfig:
    """The recipe's settings for the first of `names` it has a file for."""
    folder = directory / RECIPE / recipe
    if not folder.is_dir():
        known = (
            sorted(p.name for p in (directory / RECIPE).iterdir() if p.is_dir())
            if (directory / RECIPE).is_dir()
            else []
        )
        raise ConfigError(f"recipe={recipe}: no {folder}; recipes: {', '.join(known) or 'none'}")
    for candidate in names:
        if (folder / f"{candidate}.yaml").is_file():
            return _load_yaml(folder / f"{candidate}.yaml")
    raise ConfigError(
        f"recipe={recipe} has no settings for {names[0]} (it covers: "
        f"{', '.join(sorted(p.stem for p in folder.glob('*.yaml')))})"
    )


def compose(
    name: str, overrides: Sequence[str] = (), schema: type | None = None, directory: Path | None = None
) -> DictConfig:
    """Compose conf/<name>.yaml with its defaults and `overrides`; validate against `schema`."""
    directory = directory or conf_dir()
    if not directory.is_dir():
        raise ConfigError(
            f"{directory}: no config folder there; set {CONF_DIR_VARIABLE} to a folder of configs "
            "(the repository's conf/ or a copy of it), or reinstall the package, whose wheel carries them"
        )
    primary = _load_yaml(directory / f"{name}.yaml")
    # `extends: other` starts from conf/other.yaml (its defaults included) and changes a few keys.
    base_name = primary.pop("extends", None)
    if base_name is not None:
        base = _load_yaml(directory / f"{base_name}.yaml")
        if "extends" in base:
            raise ConfigError(
                f"{directory / name}.yaml extends {base_name}.yaml, which extends another: one level only"
            )
        base_defaults = list(base.pop("defaults", []))
        own = list(primary.pop("defaults", []))
        primary = OmegaConf.merge(base, primary)
        primary["defaults"] = base_defaults + own  # later entries of a group win below
    defaults = primary.pop("defaults", [])
    choices = _choices(defaults, directory / f"{name}.yaml")

    dotted, chosen, recipe = [], {}, None
    for item in overrides:
        if "=" not in item:
            raise ConfigError(
                f"override {item!r} is not key=value (e.g. trainer.max_steps=500 or model=paper)"
            )
        key, value = item.split("=", 1)
        if key == RECIPE:
            recipe = value
        elif "." not in key and (directory / key).is_dir():
            if not (directory / key / f"{value}.yaml").exists():
                raise ConfigError(
                    f"{key}={value}: no {directory / key / value}.yaml; options: "
                    f"{', '.join(_options(directory, key))}"
                )
            chosen[key] = value
        else:
            dotted.append(item)
    recipe_cfg = _recipe(directory, recipe, [name] + ([base_name] if base_name else [])) if recipe else None
    if recipe_cfg is not None:
        choices.update(_choices(recipe_cfg.pop("defaults", []), directory / RECIPE / recipe))
    choices.update(chosen)

    cfg = OmegaConf.create({})
    for group, option in choices.items():
        group_cfg = _load_option(directory, group, option)
        cfg = OmegaConf.merge(cfg, {group: group_cfg})
    try:
        cfg = OmegaConf.merge(cfg, primary, recipe_cfg or {}, OmegaConf.from_dotlist(dotted))
        if schema is not None:
            cfg = OmegaConf.merge(OmegaConf.structured(schema), cfg)
    except OmegaConfBaseException as e:
        # OmegaConf's first line names the key (and a close match); the lines after it (full_key,
        # reference_type, object_type) are its debugging context, which a one-line error leaves out.
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(f"config {name!r} with overrides {list(overrides)}: {reason}") from None
    OmegaConf.set_struct(cfg, True)
    if schema is not None:
        to_object(cfg)  # the schema's own checks (__post_init__), now rather than when a command starts
    return cfg


def to_object(cfg: DictConfig) -> Any:
    """The dataclass instance (schemas) behind a composed config."""
    return OmegaConf.to_object(cfg)


def config_hash(cfg: DictConfig) -> str:
    """Short stable hash of a resolved config (tags runs and registered models)."""
    text = OmegaConf.to_yaml(cfg, resolve=True, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def as_config(cls: type, value):
    """`value` as a `cls` dataclass: a dict (as checkpoints keep hyper-parameters) is unpacked,
    anything else is returned as it is."""
    return cls(**value) if isinstance(value, dict) else value
