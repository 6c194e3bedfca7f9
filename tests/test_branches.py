"""Forecast branches: one branch is the paper's window (same numbers), every branch is the paper's forecast from its
own history, the forecasts feed back their own reparameterised samples, rows past an episode's end never count, and
a run with branches resumes to the same weights."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
from synthetic_dynamics import SPEC, write_linear_dataset

from rwm_gym.model import MODEL_KINDS, Prediction, build_model, model_config_for
from rwm_gym.model.branches import branch_starts, branched_forecast
from rwm_gym.model.checkpoint import read_meta
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.factory import train_config_for
from rwm_gym.model.losses import segment_loss, window_loss
from rwm_gym.model.train import train
from rwm_gym.model.windows import Window

TINY = dict(hidden_size=16, num_layers=2, head_hidden=16, transformer_dim=16, transformer_context=6, rssm_latent=4)
S, A, C, F = SPEC.state_dim, SPEC.action_dim, SPEC.contact_dim, SPEC.foot_dim
LEARNED = [k for k in MODEL_KINDS if k != "no_change"]


def tiny(kind: str, ensemble: int = 1):
    torch.manual_seed(0)
    return build_model(model_config_for(kind, SPEC, **TINY, ensemble_size=ensemble)).train()


def random_window(batch: int, rows: int) -> Window:
    g = torch.Generator().manual_seed(1)
    return Window(
        torch.randn(batch, rows, S, generator=g),
        torch.rand(batch, rows, A, generator=g) * 2 - 1,
        (torch.rand(batch, rows, C, generator=g) > 0.5).float(),
        torch.randn(batch, rows, F, generator=g),
        (torch.rand(batch, rows, generator=g) > 0.8).float(),
    )


def loss_and_grads(fn, model, window, config, member):
    torch.manual_seed(5)
    model.zero_grad()
    loss, parts = fn(model, window, config, 2.0, member)
    loss.backward()
    grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    return loss.detach(), {k: float(v) for k, v in parts.items()}, grads


@pytest.mark.parametrize("kind", LEARNED)
@pytest.mark.parametrize("ensemble", [1, 3])
def test_one_branch_is_the_papers_window(kind: str, ensemble: int) -> None:
    """The same loss, parts and gradients as `window_loss`, to float rounding (the teacher-forced pass runs all its
    rows as one batch)."""
    model, window = tiny(kind, ensemble), random_window(4, 9)
    member = torch.tensor([0, 2, 1, 0]) if ensemble > 1 else None
    config = TrainConfig(history=5, forecast=4)
    old = loss_and_grads(window_loss, model, window, config, member)
    new = loss_and_grads(segment_loss, model, window, config, member)
    torch.testing.assert_close(new[0], old[0], rtol=1e-6, atol=0)
    assert new[1] == pytest.approx(old[1], rel=1e-6, abs=1e-7)
    assert old[2].keys() == new[2].keys()
    for name, grad in old[2].items():
        torch.testing.assert_close(new[2][name], grad, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("kind", LEARNED)
def test_every_branch_is_the_papers_forecast_from_its_own_history(kind: str, monkeypatch) -> None:
    """With the samples replaced by the means, branch i equals `WorldModel.forecast` over rows 0..j_i of its segment
    (history j_i + 1 rows), whether its first step is read from the teacher-forced pass or recomputed."""
    model = tiny(kind, ensemble=2).eval()  # eval: RSSM uses its latent means, so both paths are deterministic
    config = TrainConfig(history=4, forecast=3, branches=3, branch_stride=2, batch_size=6)
    window, member = random_window(2, config.segment_rows), torch.tensor([1, 0])
    monkeypatch.setattr(Prediction, "sample", lambda self: self.state_mean)
    with torch.no_grad():
        branches, _ = branched_forecast(model, window.states, window.actions, config, member)
        for i, j in enumerate(branch_starts(config).tolist()):
            paper, _ = model.forecast(
                window.states[:, : j + 1], window.actions, config.forecast, sample=False, member=member
            )
            for name in ("state_mean", "state_std", "contact_logits", "foot_height", "termination_logit"):
                torch.testing.assert_close(getattr(branches, name)[i :: config.branches], getattr(paper, name))


@pytest.mark.parametrize("kind", ["rwm", "rssm"])  # first step read from the teacher-forced pass / recomputed
def test_branches_feed_back_their_own_samples_with_gradients(kind: str, monkeypatch) -> None:
    """A spy on `step`: after the first, every forecast step of every branch is fed the sample drawn from its own
    previous prediction (in the autograd graph), never the true row; teacher forcing would fail it."""
    model = tiny(kind)
    config = TrainConfig(history=4, forecast=4, branches=3, batch_size=6)
    window = random_window(2, config.segment_rows)
    samples, inputs = [], []
    original_sample, original_step = Prediction.sample, model.step

    def spy_sample(self):
        samples.append(original_sample(self))
        return samples[-1]

    def spy_step(hidden, state, action, member=None, next_state=None):
        if next_state is None:  # forecast steps (RSSM's teacher-forced pass steps with the true next state)
            inputs.append(state)
        return original_step(hidden, state, action, member, next_state)

    monkeypatch.setattr(Prediction, "sample", spy_sample)
    monkeypatch.setattr(model, "step", spy_step)
    prediction, _ = branched_forecast(model, window.states, window.actions, config)
    fed = inputs[-(config.forecast - 1) :]  # the steps after the first
    true_next = window.states[:, branch_starts(config).unsqueeze(1) + 1 + torch.arange(config.forecast)].flatten(0, 1)
    for k, state in enumerate(fed, start=1):
        assert state is samples[k - 1] and state.requires_grad
        assert not torch.allclose(state, true_next[:, k - 1])
    prediction.state_mean[:, -1].sum().backward()
    assert model.heads.state.hidden.weight.grad.abs().sum() > 0


TRUNCATABLE = [k for k in LEARNED if k != "rssm"]


@pytest.mark.parametrize("kind", TRUNCATABLE)
def test_without_warmup_gradients_the_loss_is_the_same_and_the_warmup_gets_none(kind: str) -> None:
    """`warmup_gradients` off changes the gradients only: the same loss (first steps recomputed instead of read from
    the pass), no gradient into the rows before the first branch's last true row, and gradients there when on."""
    model = tiny(kind, ensemble=2)
    full = TrainConfig(history=5, forecast=3, branches=3, branch_stride=2, batch_size=6)
    truncated = TrainConfig(**{**full.to_dict(), "warmup_gradients": False})
    window, member = random_window(2, full.segment_rows), torch.tensor([1, 0])
    first = int(branch_starts(full)[0])
    losses, warmup_grads = [], []
    for config in (full, truncated):
        states = window.states.clone().requires_grad_()
        torch.manual_seed(5)
        loss, _ = segment_loss(model, dataclasses.replace(window, states=states), config, 2.0, member)
        loss.backward()
        losses.append(loss.detach())
        warmup_grads.append(states.grad[:, :first].abs().sum())
        assert states.grad[:, first].abs().sum() > 0  # each branch's last true row still feeds its first step
    torch.testing.assert_close(losses[1], losses[0], rtol=1e-5, atol=0)
    assert warmup_grads[0] > 0 and warmup_grads[1] == 0


def test_without_warmup_gradients_a_model_whose_warmup_has_its_own_loss_is_refused() -> None:
    config = TrainConfig(history=4, forecast=2, warmup_gradients=False)
    window = random_window(2, config.segment_rows)
    with pytest.raises(ValueError, match="rssm"):
        segment_loss(tiny("rssm"), window, config, 2.0)


def test_one_trainer_setting_for_every_kind_keeps_rssms_warmup_gradients() -> None:
    """`train_config_for`: what the benchmarks give every kind. Only a model whose warm-up carries its own loss
    (rssm) gets its warm-up gradients back; the others train as configured."""
    truncated = TrainConfig(warmup_gradients=False)
    assert train_config_for("rssm", truncated).warmup_gradients is True
    assert all(train_config_for(kind, truncated) is truncated for kind in TRUNCATABLE)
    assert train_config_for("rssm", TrainConfig()) == TrainConfig()


def test_configs_written_before_warmup_gradients_load_with_it_on() -> None:
    legacy = {k: v for k, v in TrainConfig().to_dict().items() if k != "warmup_gradients"}
    assert TrainConfig.from_dict(legacy).warmup_gradients is True


def test_forecasts_past_an_episodes_end_do_not_count() -> None:
    """Rows beyond a segment's real rows change nothing in the loss; the branches before them still count."""
    model = tiny("rwm")
    config = TrainConfig(history=4, forecast=3, branches=4, batch_size=8)
    window = random_window(2, config.segment_rows)
    real_rows = torch.tensor([config.segment_rows, config.segment_rows - 2])  # segment 1 loses its last 2 branches

    def loss(w):
        torch.manual_seed(3)
        return segment_loss(model, w, config, 2.0, real_rows=real_rows)[0]

    base = loss(window)
    garbage = window.map(lambda t: t.clone())
    garbage.states[1, -2:] += 100.0
    garbage.terminated[1, -2:] = 1.0
    torch.testing.assert_close(loss(garbage), base)
    assert not torch.equal(loss(window.map(lambda t: t.clone().fill_(0.5))), base)


def test_legacy_train_config_reads_as_one_branch() -> None:
    old = {k: v for k, v in TrainConfig().to_dict().items() if k not in ("branches", "branch_stride")}
    config = TrainConfig.from_dict(old)
    assert config.branches == 1 and config.segment_rows == config.history + config.forecast
    with pytest.raises(ValueError, match="divide batch_size"):
        TrainConfig(batch_size=10, branches=4)


@pytest.mark.parametrize("kind,warmup_gradients", [("rwm", True), ("transformer", True), ("rwm", False)])
def test_run_with_branches_resumes_to_the_same_weights(kind: str, warmup_gradients: bool, tmp_path: Path) -> None:
    data = write_linear_dataset(tmp_path / "linear.h5")
    config = model_config_for(kind, SPEC, **TINY, ensemble_size=2)
    run = TrainConfig(
        history=6,
        forecast=3,
        batch_size=12,
        branches=4,
        branch_stride=2,
        iterations=8,
        val_every=4,
        checkpoint_every=3,
        val_fraction=0.25,
        warmup_gradients=warmup_gradients,
    )
    full = train(data, config, run, progress=False).model.state_dict()

    def interrupt_at_5(iteration: int, stats: dict) -> None:
        if iteration == 5:
            raise KeyboardInterrupt

    out = tmp_path / "resumed.safetensors"
    with pytest.raises(KeyboardInterrupt):
        train(data, config, run, out, progress=False, callback=interrupt_at_5)
    resumed = train(data, config, run, out, resume=True, progress=False)
    assert resumed.stats["iterations"] == 8
    assert all(torch.equal(full[k], v) for k, v in resumed.model.state_dict().items())
    assert read_meta(out).train_config.warmup_gradients is warmup_gradients  # saved with the run it describes
