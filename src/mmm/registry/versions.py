"""Registered models, their versions' tags, and the champion/challenger decision.

Three registered models (MLflow Model Registry, aliases rather than the deprecated stages):
    mmm-tokenizer     stage-1 checkpoints  (source runs:/<stage-1 run>/checkpoints)
    mmm-text2motion   the pyfunc bundle    (tokenizer + transformer + normalization + text encoder)
    mmm-evaluator     the own evaluator    (source runs:/<evaluator run>/checkpoints)
Every version is tagged with what its decision needs: the criteria's metrics (`metric.<name>`,
and `metric.<name>_ci` where the metric has a confidence interval), the data fingerprint, the
evaluator identity its metrics came from, the config hash, the code version, the identities of
its parts, and `promotion` (alias and reason). The alias `champion` moves to a candidate only when
it beats the current champion on every configured metric by the configured margin, measured on the
same data fingerprint with the same evaluator; otherwise the candidate gets `challenger`. The
version's description (markdown, shown by the dashboard) says what the model is, the criteria,
both values, the margin needed, the verdict with its reason, and links to the run that measured
it and to the previous champion. A bundle version is linked to its logged model (the model's page
shows its registered versions).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import math
import shutil
import subprocess
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlparse

from mlflow.exceptions import MlflowException
from mlflow.utils.mlflow_tags import MLFLOW_MODEL_VERSIONS

from mmm import __version__
from mmm.atomic import sha256_file
from mmm.kinds import PROMOTABLE
from mmm.registry.configs import Criterion, criteria_errors
from mmm.resolve import log_artifact_with_digest
from mmm.tracking import git_commit, run_link, sqlite_database, version_link

# The registered models, by what `mmm promote` calls them (kinds.py holds the names).
TOKENIZER, TEXT2MOTION, EVALUATOR, UPPERBODY = (
    PROMOTABLE[k].registered for k in ("tokenizer", "text2motion", "evaluator", "upperbody")
)


@dataclass
class Decision:
    promoted: bool
    alias: str  # champion | challenger
    reason: str
    version: str
    previous_champion: str | None = None
    comparisons: list[str] = field(default_factory=list)


NO_CHAMPION = "the first version promoted (no champion yet)"  # the reason a first version wins
CI_SUFFIX = "_ci"  # the protocol's interval of a metric (1.96·std/sqrt(n)), logged alongside it


def code_version() -> str:
    """The git commit of this package's source checkout ("+dirty" when it has changes); for an
    installed (non-editable) package, or without git, the package version ("mmm-motion 0.1.0")."""
    fallback = f"mmm-motion {__version__}"
    root = Path(__file__).resolve().parents[3]
    commit = git_commit(root)
    if commit is None:
        return fallback
    try:
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        dirty = ""
    return commit + ("+dirty" if dirty else "")


PROTOCOL_HASH, PROTOCOL_SETTINGS = "protocol.hash", "protocol.settings"
WEIGHTS_SHA256 = "weights.sha256"


def protocol_hash(settings: dict) -> str:
    """Short sha256 of how metrics were measured (split, protocol, length rules, evaluator, ...)."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


def version_tags(
    metrics: dict[str, float],
    data_fingerprint: str,
    evaluator: str | None,
    config_hash: str | None,
    extra: dict | None = None,
    protocol: dict | None = None,
) -> dict[str, str]:
    """A version's tags: its finite metrics (NaN and infinite values are left out: not measured),
    what they were measured on and with, and `protocol` (how: `protocol.hash`, and the settings
    as JSON in `protocol.settings`)."""
    tags = {
        f"metric.{k}": repr(float(v)) for k, v in metrics.items() if v is not None and math.isfinite(float(v))
    }
    tags.update(
        {
            "data.fingerprint": data_fingerprint,
            "evaluator": evaluator or "",
            "config.hash": config_hash or "",
            "code.version": code_version(),
        }
    )
    if protocol is not None:
        tags[PROTOCOL_HASH] = protocol_hash(protocol)
        tags[PROTOCOL_SETTINGS] = json.dumps(protocol, sort_keys=True, default=str)[
            :4900
        ]  # the store's tag limit is 5000
    tags.update({k: str(v) for k, v in (extra or {}).items()})
    return tags


def freeze_weights(client, run_id: str, checkpoint: str | Path, name: str) -> tuple[str, str]:
    """(source, sha256) of an immutable copy of `checkpoint` for a version of `name`: logged into
    run `run_id` as `registered/<name>-<sha256[:12]>/best.ckpt`, a path no training writes (a
    resumed run re-uploads `checkpoints/`, never this). The same file registered twice shares it."""
    digest = sha256_file(checkpoint)
    folder = f"registered/{name}-{digest[:12]}"
    if not any(f.path == f"{folder}/best.ckpt" for f in client.list_artifacts(run_id, folder)):
        with (
            tempfile.TemporaryDirectory() as tmp
        ):  # the artifact keeps its name best.ckpt whatever the local file's
            local = Path(tmp) / "best.ckpt"
            shutil.copyfile(checkpoint, local)
            log_artifact_with_digest(
                client, run_id, local, folder
            )  # the run records its digest too (the download cache's key)
    return f"runs:/{run_id}/{folder}", digest


def register_version(
    client,
    name: str,
    source: str,
    run_id: str | None,
    tags: dict[str, str],
    description: str = "",
    model_description: str | None = None,
):
    """A new version of `name` (created if missing) with `tags`. `source` is runs:/ID/PATH or a
    logged model's models:/m-ID; for the latter the version is registered as the logged model's
    (its id passed along) and the logged model records the version, as `mlflow.register_model`
    does, so the model's page shows it as registered. `model_description`: the registered model's
    own, when this creates it (default: `description`)."""
    try:
        client.get_registered_model(name)
    except MlflowException:
        try:
            client.create_registered_model(
                name,
                tags={"mmm.kind": name.removeprefix("mmm-")},
                description=description if model_description is None else model_description,
            )
        except MlflowException as e:  # another process created it meanwhile
            if "ALREADY_EXISTS" not in str(e.error_code):
                raise
    model_id = source[len("models:/") :] if source.startswith("models:/m-") else None
    version = client.create_model_version(
        name, source, run_id=run_id, tags=tags, description=description, model_id=model_id
    )
    if model_id:
        link_logged_model(client, model_id, name, version.version)
    return version


def registered_before(client, name: str, run_id: str, same: dict[str, str]):
    """The version of `name` already registered from run `run_id` whose tags hold `same` (e.g. the
    weights' sha256), or None: promoting the same weights again re-measures that version rather
    than registering a copy of it (a copy of the champion would become its own challenger)."""
    for version in sorted(client.search_model_versions(f"name='{name}'"), key=lambda v: int(v.version)):
        if version.run_id == run_id and all(version.tags.get(k) == v for k, v in same.items()):
            return version
    return None


def retag_version(client, name: str, version, tags: dict[str, str]):
    """`version` measured anew: `tags` set over its own, and its `metric.*` tags that the new
    measurement lacks removed (they would mix two measurements); returns it as it is now."""
    for key in version.tags:
        if key.startswith("metric.") and key not in tags:
            client.delete_model_version_tag(name, version.version, key)
    for key, value in tags.items():
        client.set_model_version_tag(name, version.version, key, value)
    return client.get_model_version(name, version.version)


def link_logged_model(client, model_id: str, name: str, version) -> None:
    """Record `name` `version` on logged model `model_id` the way `mlflow.register_model` does (its
    `mlflow.modelVersions` tag, a JSON list of {name, version}), which the dashboard reads for the
    model's "Registered" state. A tracking server already writes it when the version is created
    with the model id; an entry already there is not added twice."""
    existing = client.get_logged_model(model_id).tags.get(MLFLOW_MODEL_VERSIONS)
    entries = json.loads(existing) if existing else []
    if any(e.get("name") == name and str(e.get("version")) == str(version) for e in entries):
        return
    client.set_logged_model_tags(
        model_id, {MLFLOW_MODEL_VERSIONS: json.dumps([*entries, {"name": name, "version": version}])}
    )


def _metric(version, name: str) -> float | None:
    value = version.tags.get(f"metric.{name}")
    return float(value) if value not in (None, "") else None


def _target(c: Criterion, old: float) -> float:
    return old - c.margin if c.mode == "min" else old + c.margin


def _is_better(c: Criterion, new: float, old: float) -> bool:
    # Strictly: a tie (the same model trained again) does not take the alias.
    return new < _target(c, old) if c.mode == "min" else new > _target(c, old)


def _relation(c: Criterion) -> str:
    return "<" if c.mode == "min" else ">"


def _unmeasured(candidate, criteria: list[Criterion]) -> list[str]:
    """The criteria's metrics the candidate has no finite value for."""
    missing = []
    for c in criteria:
        raw = candidate.tags.get(f"metric.{c.metric}")
        try:
            value = float(raw)
        except (TypeError, ValueError):
            value = math.nan
        if not math.isfinite(value):
            missing.append(f"{c.metric} {'missing' if raw in (None, '') else f'is {raw}'}")
    return missing


def _protocol_difference(candidate, champion) -> str | None:
    """Why the two versions' metrics were measured otherwise, or None when the same way."""
    ours, theirs = candidate.tags.get(PROTOCOL_HASH), champion.tags.get(PROTOCOL_HASH)
    if ours == theirs:
        return None
    try:
        a, b = (
            json.loads(candidate.tags.get(PROTOCOL_SETTINGS) or "{}"),
            json.loads(champion.tags.get(PROTOCOL_SETTINGS) or "{}"),
        )
    except ValueError:
        a, b = {}, {}
    differing = [
        f"{k} {a.get(k, '-')} vs {b.get(k, '-')}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)
    ]
    detail = (
        "; ".join(differing[:6])
        if differing
        else f"protocol {ours or 'not recorded'} vs {theirs or 'not recorded'}"
    )
    return (
        f"measured with another protocol than the champion ({detail}): re-evaluate both with the same split, "
        "protocol, length "
        "rules and evaluator to compare"
    )


def decide(
    candidate, champion, criteria: list[Criterion], needs_evaluator: bool
) -> tuple[bool, str, list[str]]:
    """(promote?, reason, per-metric comparisons) for a candidate version against the champion.
    A candidate without a finite value for every criterion never promotes, champion or not."""
    unmeasured = _unmeasured(candidate, criteria)
    if unmeasured:
        return (
            False,
            "not measured: " + "; ".join(unmeasured) + " (a missing, NaN or infinite metric never promotes)",
            [],
        )
    if champion is None:
        return True, NO_CHAMPION, []
    if candidate.tags.get("data.fingerprint") != champion.tags.get("data.fingerprint"):
        return (
            False,
            (
                f"measured on other data (fingerprint {candidate.tags.get('data.fingerprint')} vs the "
                "champion's "
                f"{champion.tags.get('data.fingerprint')}): re-evaluate both on the same data to compare"
            ),
            [],
        )
    if needs_evaluator and candidate.tags.get("evaluator") != champion.tags.get("evaluator"):
        return (
            False,
            (
                f"measured with another evaluator ({candidate.tags.get('evaluator')} vs the champion's "
                f"{champion.tags.get('evaluator')}): re-evaluate both with the same evaluator to compare"
            ),
            [],
        )
    protocol = _protocol_difference(candidate, champion)
    if protocol:
        return False, protocol, []
    comparisons, failures = [], []
    for c in criteria:
        new, old = _metric(candidate, c.metric), _metric(champion, c.metric)
        if new is None or old is None:
            failures.append(f"{c.metric} missing ({'candidate' if new is None else 'champion'})")
            continue
        better = _is_better(c, new, old)
        line = (
            f"{c.metric}: {new:.4g} vs champion {old:.4g} (needs {_relation(c)} {_target(c, old):.4g}): "
            f"{'better' if better else 'not better'}"
        )
        comparisons.append(line)
        if not better:
            failures.append(line)
    if failures:
        return False, "does not beat the champion: " + "; ".join(failures), comparisons
    return True, "beats the champion on " + ", ".join(c.metric for c in criteria), comparisons


def promote_version(
    client,
    name: str,
    version: str,
    criteria: list[Criterion],
    needs_evaluator: bool = True,
    about: str = "",
    measured: str = "",
) -> Decision:
    """Give `version` of `name` the alias champion (if it beats the current one) or challenger, and
    write why into its description. `about`: what the model is (default: the version's description
    as registered); `measured`: how its metrics were measured (one sentence)."""
    problems = criteria_errors(criteria, "criteria")
    if problems:
        raise ValueError("; ".join(problems))
    with promotion_lock(client, name):
        return _promote_locked(client, name, version, criteria, needs_evaluator, about, measured)


def _store_folder(client) -> Path | None:
    """The folder of a local tracking/registry store (sqlite file, file store), None for a server."""
    uri = getattr(client, "_registry_uri", None) or client.tracking_uri
    database = sqlite_database(uri)
    if database is not None:
        return Path(database).resolve().parent
    parsed = urlparse(uri)
    if parsed.scheme == "file":
        return Path(parsed.path).resolve()
    if parsed.scheme == "" and uri:
        return Path(uri).resolve()
    return None


@contextmanager
def promotion_lock(client, name: str):
    """Serialize promotions of `name` on one local store: read the champion, decide and move the
    alias as one step (fcntl.flock on `<store folder>/.mmm-promote-<name>.lock`), so two promotions
    at once cannot leave the worse model champion. Against a tracking server it does nothing
    (`promote_version` re-checks the champion after moving the alias)."""
    folder = _store_folder(client)
    if folder is None:
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / f".mmm-promote-{name}.lock", "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)  # released when the file is closed
        yield


def _champion(client, name: str):
    try:
        return client.get_model_version_by_alias(name, "champion")
    except MlflowException:
        return None


def _promote_locked(
    client,
    name: str,
    version: str,
    criteria: list[Criterion],
    needs_evaluator: bool,
    about: str,
    measured: str,
) -> Decision:
    candidate = client.get_model_version(name, version)
    champion = _champion(client, name)
    if champion is not None and champion.version == candidate.version:
        decision = Decision(True, "champion", "already the champion", candidate.version, champion.version)
        if not _registered_about(candidate) and candidate.description:
            return decision  # its promotion's tag and description still say why it is the champion
        champion = None  # described as itself: there is no other version to compare with
    else:
        promoted, reason, comparisons = decide(candidate, champion, criteria, needs_evaluator)
        alias = "champion" if promoted else "challenger"
        client.set_registered_model_alias(name, alias, candidate.version)
        if promoted and _store_folder(client) is None:
            # A server store has no lock: if another promotion moved the alias meanwhile, decide
            # again against the version that now holds it and give it back when that one is better.
            now = _champion(client, name)
            if now is not None and now.version != candidate.version:
                if decide(candidate, now, criteria, needs_evaluator)[0]:
                    client.set_registered_model_alias(name, "champion", candidate.version)
                else:
                    promoted, alias = False, "challenger"
                    reason = (
                        f"another promotion made v{now.version} champion meanwhile, which this version does "
                        "not beat"
                    )
                    client.set_registered_model_alias(name, alias, candidate.version)
        client.set_model_version_tag(name, candidate.version, "promotion", f"{alias}: {reason}")
        decision = Decision(
            promoted, alias, reason, candidate.version, champion.version if champion else None, comparisons
        )
    text = describe_version(
        client, name, candidate, champion, criteria, decision, about or _registered_about(candidate), measured
    )
    client.update_model_version(name, candidate.version, description=text)
    if decision.promoted and champion is not None and champion.version != candidate.version:
        _note_replaced(client, name, champion, candidate.version)
    return decision


def _note_replaced(client, name: str, previous, version) -> None:
    """Tell the previous champion's description who took the alias, and when."""
    note = f"- **Replaced** as champion by {version_link(name, version)} on {time.strftime('%Y-%m-%d %H:%M')}"
    client.update_model_version(
        name, previous.version, description="\n".join(filter(None, [previous.description or "", note]))
    )


_DESCRIPTION_TITLE = "### "


def _registered_about(version) -> str:
    """The description a version was registered with, unless it is a promotion's own (re-promoted)."""
    text = (version.description or "").strip()
    return "" if text.startswith(_DESCRIPTION_TITLE) else text


def _value(version, metric: str) -> str:
    value = _metric(version, metric) if version is not None else None
    if value is None:
        return "not measured"
    ci = _metric(version, metric + CI_SUFFIX)
    return f"{value:.4g}" + (f" ± {ci:.2g}" if ci is not None else "")


def describe_version(
    client,
    name: str,
    candidate,
    champion,
    criteria: list[Criterion],
    decision: Decision,
    about: str = "",
    measured: str = "",
) -> str:
    """The version's markdown description: what it is, the criteria with both values and the
    margin needed, the verdict and its reason, the run that measured it, the previous champion."""
    tags = candidate.tags
    verdict = "promoted to `champion`" if decision.promoted else "`challenger`, not promoted"
    lines = [f"{_DESCRIPTION_TITLE}{name} v{candidate.version}: {verdict}", ""]
    if about:
        lines += [about, ""]
    lines += [f"**Verdict: {decision.alias}.** {decision.reason[:1].upper()}{decision.reason[1:]}.", ""]
    compared = champion is not None and not decision.reason.startswith("measured ")
    champion_head = f"champion (v{champion.version})" if champion is not None else "champion"
    lines += [
        f"| criterion | mode | margin | candidate (v{candidate.version}) | {champion_head} | needs | result "
        "|",
        "|---|---|---|---|---|---|---|",
    ]
    for c in criteria:
        new, old = _metric(candidate, c.metric), _metric(champion, c.metric) if champion is not None else None
        if champion is None:
            needs, result = "-", "no champion to beat" if decision.reason == NO_CHAMPION else "-"
        elif old is None:
            needs, result = "-", "champion not measured"
        else:
            needs = f"{_relation(c)} {_target(c, old):.4g}"
            if not compared:
                result = "not compared"
            elif new is None:
                result = "candidate not measured"
            else:
                result = "better" if _is_better(c, new, old) else "not better"
        mode = "min (lower is better)" if c.mode == "min" else "max (higher is better)"
        lines.append(
            f"| `{c.metric}` | {mode} | {c.margin:g} | {_value(candidate, c.metric)} | "
            f"{_value(champion, c.metric) if champion is not None else '-'} | {needs} | {result} |"
        )
    lines.append("")
    if any(_metric(candidate, c.metric + CI_SUFFIX) is not None for c in criteria):
        lines += ["± : the 95% confidence interval over the protocol's replications (1.96·std/sqrt(n)).", ""]
    facts = []
    if measured:
        facts.append(f"- **Measured**: {measured}")
    facts.append(
        f"- **Data** `{tags.get('data.fingerprint') or '?'}`"
        + (f", evaluator `{tags['evaluator']}`" if tags.get("evaluator") else "")
    )
    if tags.get(PROTOCOL_HASH):
        try:
            settings = json.loads(tags.get(PROTOCOL_SETTINGS) or "{}")
        except ValueError:
            settings = {}
        readable = ", ".join(f"{k} `{v}`" for k, v in sorted(settings.items()))
        facts.append(
            f"- **Protocol** `{tags[PROTOCOL_HASH]}`"
            + (f": {readable}" if readable else "")
            + " (only versions measured with the same protocol are compared)"
        )
    if tags.get(WEIGHTS_SHA256):
        facts.append(f"- **Weights** sha256 `{tags[WEIGHTS_SHA256]}` (checked when the version is loaded)")
    if candidate.run_id:
        try:
            run = client.get_run(candidate.run_id)
            facts.append(
                f"- **Run**: "
                f"{run_link(run.info.experiment_id, run.info.run_id, run.info.run_name or run.info.run_id)} "
                "(the model's own run: its training curves and files)"
            )
        except MlflowException:
            facts.append(f"- **Run**: `{candidate.run_id}` (no longer in this store)")
    if decision.reason == "already the champion":
        facts.append("- **Previous champion**: this version itself (promoted again)")
    elif decision.previous_champion is not None:
        after = "replaced by this version" if decision.promoted else "stays champion"
        facts.append(f"- **Previous champion**: {version_link(name, decision.previous_champion)} ({after})")
    else:
        facts.append("- **Previous champion**: none (the first version promoted)")
    facts.append(
        f"- **Source** `{candidate.source}`; code `{tags.get('code.version') or '?'}`, config hash "
        f"`{tags.get('config.hash') or '-'}`"
    )
    return "\n".join(lines + facts)


def _verdict(version) -> str:
    """`<alias>: <reason>` of the version's promotion, on one line."""
    text = version.tags.get("promotion")
    return " ".join(text.split()) if text else "not promoted (registered without a decision)"


def list_models(client, names=(TOKENIZER, TEXT2MOTION, EVALUATOR, UPPERBODY)) -> str:
    """A text table of every version of the package's registered models: its aliases, then its
    promotion's verdict and reason, then its metrics and data."""
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
            metrics = ", ".join(
                f"{k[7:]}={float(val):.4g}"
                for k, val in sorted(v.tags.items())
                if k.startswith("metric.") and not k.endswith(CI_SUFFIX) and val not in ("", None)
            )
            mark = ",".join(sorted(aliases.get(str(v.version), []))) or "-"
            lines.append(f"  v{v.version:<3} {mark:<12} {_verdict(v)}")
            lines.append(f"       data {v.tags.get('data.fingerprint') or '?'}  {metrics}")
    return "\n".join(lines)
