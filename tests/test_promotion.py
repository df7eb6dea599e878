"""Promotion: champion only for a candidate that wins on the same data with the same evaluator."""

import pytest
from mlflow.tracking import MlflowClient

from mmm.registry.configs import Criterion
from mmm.registry.versions import code_version, list_models, promote_version, register_version, version_tags


@pytest.fixture
def client(tmp_path):
    return MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")


def add(client, fid, top1=0.5, data="d1", evaluator="e1"):
    tags = version_tags({"generated/fid": fid, "generated/top1": top1}, data, evaluator, "cfg123")
    return register_version(client, "m", "runs:/0123456789abcdef0123456789abcdef/bundle", None, tags).version


CRITERIA = [Criterion("generated/fid", "min", 0.01)]


@pytest.mark.slow
def test_first_candidate_becomes_champion_and_tags_are_recorded(client):
    v1 = add(client, fid=0.5)
    decision = promote_version(client, "m", v1, CRITERIA)
    assert (decision.promoted, decision.alias, decision.reason) == (
        True,
        "champion",
        "the first version promoted (no champion yet)",
    )
    version = client.get_model_version_by_alias("m", "champion")
    assert version.version == v1
    assert version.tags["metric.generated/fid"] == "0.5" and version.tags["data.fingerprint"] == "d1"
    assert version.tags["config.hash"] == "cfg123" and version.tags["code.version"] == code_version() != ""
    assert version.tags["promotion"] == "champion: the first version promoted (no champion yet)"


@pytest.mark.slow
def test_champion_moves_only_when_beaten_by_the_margin(client):
    v1 = add(client, fid=0.5)
    promote_version(client, "m", v1, CRITERIA)
    v2 = add(client, fid=0.495)  # better, but not by 0.01
    d2 = promote_version(client, "m", v2, CRITERIA)
    assert (d2.promoted, d2.alias) == (False, "challenger")
    assert "generated/fid: 0.495 vs champion 0.5 (needs < 0.49): not better" in d2.reason
    assert client.get_model_version_by_alias("m", "champion").version == v1
    assert client.get_model_version_by_alias("m", "challenger").version == v2
    v3 = add(client, fid=0.3)
    d3 = promote_version(client, "m", v3, CRITERIA)
    assert (
        d3.promoted
        and d3.previous_champion == v1
        and client.get_model_version_by_alias("m", "champion").version == v3
    )
    # A tie is not a win, even with no margin (the same model trained again).
    tie = promote_version(client, "m", add(client, fid=0.3), [Criterion("generated/fid", "min", 0.0)])
    assert not tie.promoted and "(needs < 0.3): not better" in tie.reason
    # Every configured metric must win: better FID but a worse R-precision stays challenger.
    both = [Criterion("generated/fid", "min", 0.0), Criterion("generated/top1", "max", 0.0)]
    v4 = add(client, fid=0.1, top1=0.4)
    d4 = promote_version(client, "m", v4, both)
    assert not d4.promoted and "generated/top1: 0.4 vs champion 0.5" in d4.reason


@pytest.mark.slow
def test_other_data_or_evaluator_is_never_compared(client):
    v1 = add(client, fid=0.5)
    promote_version(client, "m", v1, CRITERIA)
    other_data = promote_version(client, "m", add(client, fid=0.01, data="d2"), CRITERIA)
    assert (
        not other_data.promoted
        and "measured on other data (fingerprint d2 vs the champion's d1)" in other_data.reason
    )
    other_eval = promote_version(client, "m", add(client, fid=0.01, evaluator="e2"), CRITERIA)
    assert (
        not other_eval.promoted
        and "measured with another evaluator (e2 vs the champion's e1)" in other_eval.reason
    )
    assert client.get_model_version_by_alias("m", "champion").version == v1
    # A metric that needs no evaluator (e.g. MPJPE) may compare across evaluators.
    mpjpe = promote_version(
        client, "m", add(client, fid=0.01, evaluator="e3"), CRITERIA, needs_evaluator=False
    )
    assert mpjpe.promoted


@pytest.mark.slow
def test_models_list_shows_versions_aliases_and_metrics(client):
    promote_version(
        client,
        "mmm-tokenizer",
        register_version(
            client,
            "mmm-tokenizer",
            "runs:/0123456789abcdef0123456789abcdef/checkpoints",
            None,
            version_tags({"recon/mpjpe_root_aligned_mm": 31.4}, "d1", None, None),
        ).version,
        [Criterion("recon/mpjpe_root_aligned_mm")],
    )
    text = list_models(client)
    assert "mmm-tokenizer:" in text and "v1   champion" in text and "recon/mpjpe_root_aligned_mm=31.4" in text
    assert "mmm-text2motion: not registered yet" in text


def test_code_version_is_the_commit_of_a_checkout_and_the_package_version_otherwise(tmp_path, monkeypatch):
    import subprocess

    import mmm
    from mmm.registry import versions as promotion

    head = subprocess.run(
        ["git", "-C", str(promotion.Path(promotion.__file__).parents[3]), "rev-parse", "HEAD"],
        capture_output=True,
        text=True,
    ).stdout.strip()
    if head:  # this checkout is a git clone (CI's is)
        assert code_version().removesuffix("+dirty") == head
    # A copy of the module outside a checkout (as in site-packages, inside some other repository).
    fake = tmp_path / "lib" / "python3" / "site-packages" / "mmm" / "registry" / "promotion.py"
    fake.parent.mkdir(parents=True)
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    monkeypatch.setattr(promotion, "__file__", str(fake))
    assert code_version() == f"mmm-motion {mmm.__version__}"
