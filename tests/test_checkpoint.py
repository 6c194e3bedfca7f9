"""Checkpoints: save then load predicts identically for every kind; wrong layouts, truncated or foreign files and
shape mismatches fail in one line naming the file and what differs; saves are atomic."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from synthetic_dynamics import SPEC

from rwm_gym.model import MODEL_KINDS, build_model, model_config_for
from rwm_gym.model.checkpoint import CheckpointError, load_checkpoint, read_meta, save_checkpoint
from rwm_gym.model.config import TrainConfig
from rwm_gym.spec import parse_spec

TINY = dict(hidden_size=16, num_layers=1, head_hidden=16, transformer_dim=16, transformer_context=6, rssm_latent=4)


def saved(path: Path, kind: str = "rwm", **options) -> Path:
    torch.manual_seed(0)
    model = build_model(model_config_for(kind, SPEC, **{**TINY, **options}))
    return save_checkpoint(
        path,
        model,
        SPEC,
        train_config=TrainConfig(iterations=7),
        provenance={"dataset": "d.h5", "sha256": "ab"},
        stats={"iterations": 7},
        extras={"reset": {"episodes": [1, 2]}},
    )


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_save_then_load_predicts_identically(kind: str, tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = build_model(model_config_for(kind, SPEC, **TINY, ensemble_size=2)).eval()
    path = save_checkpoint(tmp_path / "m.safetensors", model, SPEC, extras={"note": "x"})
    loaded, meta = load_checkpoint(path, expect_spec=SPEC)
    assert type(loaded) is type(model) and meta.model_config == model.config and not loaded.training
    assert meta.extras == {"note": "x"} and meta.spec.state_columns == SPEC.state_columns
    assert (meta.normalizer.state_std == SPEC.state_std).all() and meta.package_version
    g = torch.Generator().manual_seed(3)
    states, actions = torch.randn(5, 8, SPEC.state_dim, generator=g), torch.rand(5, 11, SPEC.action_dim, generator=g)
    with torch.no_grad():
        a, _ = model.forecast(states, actions, 4, sample=False)
        b, _ = loaded.forecast(states, actions, 4, sample=False)
    for name in ("state_mean", "state_std", "contact_logits", "foot_height", "termination_logit", "uncertainty"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert [p.name for p in tmp_path.iterdir()] == ["m.safetensors"]  # no temp file left behind


def test_metadata_round_trip(tmp_path: Path) -> None:
    meta = read_meta(saved(tmp_path / "m.safetensors"))
    assert meta.train_config == TrainConfig(iterations=7) and meta.stats == {"iterations": 7}
    assert meta.provenance["sha256"] == "ab" and meta.extras["reset"]["episodes"] == [1, 2]
    assert meta.spec.text == SPEC.text


def test_checkpoint_of_another_layout_is_refused(tmp_path: Path) -> None:
    path = saved(tmp_path / "m.safetensors")
    blocks = SPEC.text.split("[[state]]")  # keep the first two state groups (6 columns) and the rest of the spec
    small = parse_spec("[[state]]".join(blocks[:3]) + SPEC.text[SPEC.text.index("[privileged]") :])
    assert small.state_dim == 6
    with pytest.raises(CheckpointError, match=r"m\.safetensors: .*state layout has 45 columns, expected 6"):
        load_checkpoint(path, expect_spec=small)
    renamed = parse_spec(SPEC.text.replace('name = "joint_torque"', 'name = "joint_effort"'))
    with pytest.raises(
        CheckpointError, match="state column 33 is 'joint_torque/LF_HAA', expected 'joint_effort/LF_HAA'"
    ):
        load_checkpoint(path, expect_spec=renamed)


def test_truncated_and_foreign_files_fail_in_one_line(tmp_path: Path) -> None:
    path = saved(tmp_path / "m.safetensors")
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    for bad, pattern in (
        (cut, "not a safetensors file or truncated"),
        (tmp_path / "junk.safetensors", "not a safetensors file or truncated"),
    ):
        if not bad.exists():
            bad.write_bytes(b"definitely not a checkpoint" * 10)
        with pytest.raises(CheckpointError, match=pattern) as err:
            load_checkpoint(bad)
        assert str(bad) in str(err.value) and "\n" not in str(err.value)
    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(2)}, str(foreign), metadata={"format": "someone-else"})
    with pytest.raises(CheckpointError, match="format 'someone-else'"):
        load_checkpoint(foreign)


def rewrite(path: Path, out: Path, header_change=None, meta_change=None) -> Path:
    with safe_open(str(path), "pt") as f:
        header, tensors = dict(f.metadata()), {k: f.get_tensor(k) for k in f.keys()}
    meta = json.loads(header["meta"])
    if meta_change:
        meta_change(meta)
    header["meta"] = json.dumps(meta)
    header.update(header_change or {})
    save_file(tensors, str(out), metadata=header)
    return out


def test_newer_version_and_shape_mismatch_are_named(tmp_path: Path) -> None:
    path = saved(tmp_path / "m.safetensors")
    newer = rewrite(path, tmp_path / "newer.safetensors", header_change={"format_version": "99"})
    with pytest.raises(CheckpointError, match="format_version '99' not supported"):
        load_checkpoint(newer)
    wider = rewrite(
        path, tmp_path / "wider.safetensors", meta_change=lambda m: m["model_config"].update(hidden_size=32)
    )
    with pytest.raises(
        CheckpointError,
        match=r"tensor 'model/state_gru\.weight_ih_l0' has shape \(48, 57\), "
        r"the model config expects \(96, 57\)",
    ):
        load_checkpoint(wider)
