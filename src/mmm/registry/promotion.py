"""Registered models, their versions' tags, and the champion/challenger decision.

Three registered models (MLflow Model Registry, aliases rather than the deprecated stages):
    mmm-tokenizer     stage-1 checkpoints  (source runs:/<stage-1 run>/checkpoints)
    mmm-text2motion   the pyfunc bundle    (tokenizer + transformer + normalization + text encoder)
    mmm-evaluator     the own evaluator    (source runs:/<evaluator run>/checkpoints)
Every version is tagged with its metrics (`metric.<name>`), the config hash, the data
fingerprint, the evaluator identity its metrics came from, and the code version. The alias
`champion` moves to a candidate only when it beats the current champion on every configured
metric by the configured margin, measured on the same data fingerprint with the same evaluator;
otherwise the candidate gets `challenger` and the decision says why.
"""

from __future__ import annotations

import math
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

TOKENIZER, TEXT2MOTION, EVALUATOR = "mmm-tokenizer", "mmm-text2motion", "mmm-evaluator"
UPPERBODY = "mmm-upperbody"  # the part-aware model (upper-body editing)


@dataclass
class Criterion:
    metric: str
    mode: str = "min"  # min: lower is better; max: higher is better
    margin: float = 0.0  # the candidate must be better by at least this much


@dataclass
class Decision:
    promoted: bool
    alias: str  # champion | challenger
    reason: str
    version: str
    previous_champion: str | None = None
    comparisons: list[str] = field(default_factory=list)


def code_version() -> str:
    """The git commit of this package's source checkout ("+dirty" when it has changes); for an
    installed (non-editable) package, or without git, the package version ("mmm-motion 0.1.0")."""
    from mmm import __version__

    fallback = f"mmm-motion {__version__}"
    root = Path(__file__).resolve().parents[3]
    # Only a source checkout: an installed package's parents may be some other repository.
    if not ((root / "pyproject.toml").is_file() and (root / "src" / "mmm" / "__init__.py").is_file()):
        return fallback
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return fallback
    return (commit + ("+dirty" if dirty else "")) if commit else fallback


def version_tags(metrics: dict[str, float], data_fingerprint: str, evaluator: str | None, config_hash: str | None, extra: dict | None = None) -> dict[str, str]:
    tags = {f"metric.{k}": repr(float(v)) for k, v in metrics.items() if v is not None and not math.isnan(float(v))}
    tags.update({"data.fingerprint": data_fingerprint, "evaluator": evaluator or "", "config.hash": config_hash or "", "code.version": code_version()})
    tags.update({k: str(v) for k, v in (extra or {}).items()})
    return tags


def register_version(client, name: str, source: str, run_id: str | None, tags: dict[str, str], description: str = ""):
    """A new version of `name` (created if missing) with `tags`. `source` is runs:/ID/PATH or a
    logged model's models:/m-ID (whose id a tracking server needs to be told as well)."""
    from mlflow.exceptions import MlflowException

    try:
        client.get_registered_model(name)
    except MlflowException:
        client.create_registered_model(name, tags={"mmm.kind": name.removeprefix("mmm-")}, description=description)
    model_id = source[len("models:/"):] if source.startswith("models:/m-") else None
    version = client.create_model_version(name, source, run_id=run_id, tags=tags, description=description, model_id=model_id)
    return version


def _metric(version, name: str) -> float | None:
    value = version.tags.get(f"metric.{name}")
    return float(value) if value not in (None, "") else None


def decide(candidate, champion, criteria: list[Criterion], needs_evaluator: bool) -> tuple[bool, str, list[str]]:
    """(promote?, reason, per-metric comparisons) for a candidate version against the champion."""
    if champion is None:
        return True, "no champion yet", []
    if candidate.tags.get("data.fingerprint") != champion.tags.get("data.fingerprint"):
        return False, (f"measured on other data (fingerprint {candidate.tags.get('data.fingerprint')} vs the champion's "
                       f"{champion.tags.get('data.fingerprint')}): re-evaluate both on the same data to compare"), []
    if needs_evaluator and candidate.tags.get("evaluator") != champion.tags.get("evaluator"):
        return False, (f"measured with another evaluator ({candidate.tags.get('evaluator')} vs the champion's "
                       f"{champion.tags.get('evaluator')}): re-evaluate both with the same evaluator to compare"), []
    comparisons, failures = [], []
    for c in criteria:
        new, old = _metric(candidate, c.metric), _metric(champion, c.metric)
        if new is None or old is None:
            failures.append(f"{c.metric} missing ({'candidate' if new is None else 'champion'})")
            continue
        # Strictly: a tie (the same model trained again) does not take the alias.
        better = new < old - c.margin if c.mode == "min" else new > old + c.margin
        relation = "<" if c.mode == "min" else ">"
        target = old - c.margin if c.mode == "min" else old + c.margin
        line = f"{c.metric}: {new:.4g} vs champion {old:.4g} (needs {relation} {target:.4g}): {'better' if better else 'not better'}"
        comparisons.append(line)
        if not better:
            failures.append(line)
    if failures:
        return False, "does not beat the champion: " + "; ".join(failures), comparisons
    return True, "beats the champion on " + ", ".join(c.metric for c in criteria), comparisons


def promote_version(client, name: str, version: str, criteria: list[Criterion], needs_evaluator: bool = True) -> Decision:
    """Give `version` of `name` the alias champion (if it beats the current one) or challenger."""
    from mlflow.exceptions import MlflowException

    candidate = client.get_model_version(name, version)
    try:
        champion = client.get_model_version_by_alias(name, "champion")
    except MlflowException:
        champion = None
    if champion is not None and champion.version == candidate.version:
        return Decision(True, "champion", "already the champion", candidate.version, champion.version)
    promoted, reason, comparisons = decide(candidate, champion, criteria, needs_evaluator)
    alias = "champion" if promoted else "challenger"
    client.set_registered_model_alias(name, alias, candidate.version)
    client.set_model_version_tag(name, candidate.version, "promotion", f"{alias}: {reason}")
    return Decision(promoted, alias, reason, candidate.version, champion.version if champion else None, comparisons)


def list_models(client, names=(TOKENIZER, TEXT2MOTION, EVALUATOR, UPPERBODY)) -> str:
    """A text table of every version of the package's registered models: aliases, metrics, data."""
    from mlflow.exceptions import MlflowException

    lines = []
    for name in names:
        try:
            model = client.get_registered_model(name)
        except MlflowException:
            lines.append(f"{name}: not registered yet")
            continue
        aliases: dict[str, list[str]] = {}
        for alias, version in (model.aliases or {}).items():
            aliases.setdefault(str(version), []).append(alias)
        lines.append(f"{name}:")
        versions = sorted(client.search_model_versions(f"name='{name}'"), key=lambda v: int(v.version))
        for v in versions:
            metrics = ", ".join(f"{k[7:]}={float(val):.4g}" for k, val in sorted(v.tags.items()) if k.startswith("metric."))
            mark = ",".join(aliases.get(str(v.version), [])) or "-"
            lines.append(f"  v{v.version:<3} {mark:<12} data {v.tags.get('data.fingerprint', '?')}  {metrics}")
            if v.tags.get("promotion"):
                lines.append(f"       {v.tags['promotion']}")
    return "\n".join(lines)
