"""The shared world-model interface: every kind steps, observes, forecasts and exposes its hidden state alike; the
forecast loop really feeds the model's own samples back."""

from __future__ import annotations

import pytest
import torch
from synthetic_dynamics import SPEC

from rwm_gym.model import MODEL_KINDS, Prediction, WorldModel, build_model, model_config_for
from rwm_gym.model import gru_step as gru_step_module
from rwm_gym.model.config import ModelConfig, TrainConfig
from rwm_gym.model.losses import window_loss
from rwm_gym.model.windows import Window

TINY = dict(hidden_size=16, num_layers=1, head_hidden=16, transformer_dim=16, transformer_context=6, rssm_latent=4)
S, A, C, F = SPEC.state_dim, SPEC.action_dim, SPEC.contact_dim, SPEC.foot_dim


def tiny(kind: str, **options) -> WorldModel:
    torch.manual_seed(0)
    return build_model(model_config_for(kind, SPEC, **{**TINY, **options}))


def random_window(batch: int, rows: int) -> Window:
    g = torch.Generator().manual_seed(1)
    return Window(
        torch.randn(batch, rows, S, generator=g),
        torch.rand(batch, rows, A, generator=g) * 2 - 1,
        (torch.rand(batch, rows, C, generator=g) > 0.5).float(),
        torch.randn(batch, rows, F, generator=g),
        torch.zeros(batch, rows),
    )


@pytest.mark.parametrize("kind", MODEL_KINDS)
@pytest.mark.parametrize("ensemble", [1, 3])
def test_every_kind_shares_the_step_interface(kind: str, ensemble: int) -> None:
    model = tiny(kind, ensemble_size=ensemble).eval()
    batch = 4
    hidden = model.initial_hidden(batch, "cpu")
    assert all(h.shape[0] == batch for h in hidden)
    state, action = torch.randn(batch, S), torch.rand(batch, A) * 2 - 1
    hidden, p = model.step(hidden, state, action)
    assert p.state_mean.shape == p.state_std.shape == (batch, S)
    assert p.contact_logits.shape == (batch, C) and p.foot_height.shape == (batch, F)
    assert p.termination_logit.shape == p.uncertainty.shape == (batch,)
    assert (p.state_std > 0).all() and torch.isfinite(p.state_mean).all()
    if kind == "no_change":
        torch.testing.assert_close(p.state_mean, state)
    # one member per rollout; with several members their disagreement is the uncertainty
    _, p_member = model.step(hidden, state, action, member=torch.tensor([0, ensemble - 1, 0, ensemble - 1]))
    assert p_member.state_mean.shape == (batch, S)
    assert (p.uncertainty > 0).all() == (ensemble > 1 and kind != "no_change")
    # hidden helpers: pick, overwrite and reset some rollouts without knowing the model's kind
    index = torch.tensor([2, 0])
    sub = model.select_hidden(hidden, index)
    assert all(h.shape[0] == 2 for h in sub)
    moved = model.scatter_hidden(hidden, torch.tensor([1, 3]), sub)
    for h, m in zip(hidden, moved):
        torch.testing.assert_close(m[1], h[2])
        torch.testing.assert_close(m[3], h[0])
    in_place = tuple(h.clone() for h in hidden)  # in place: the same rows as the copy, no new tensors
    model.scatter_hidden_(in_place, torch.tensor([1, 3]), sub)
    for m, p in zip(moved, in_place):
        torch.testing.assert_close(p, m)
    reset = model.reset_hidden(hidden, torch.tensor([True, False, False, False]))
    for h, r, fresh in zip(hidden, reset, model.initial_hidden(batch, "cpu")):
        torch.testing.assert_close(r[0], fresh[0])
        torch.testing.assert_close(r[1:], h[1:])
    # a forecast of N rows after a warm-up of H rows
    window = random_window(batch, 9)
    forecast, warm = model.forecast(window.states[:, :5], window.actions[:, :8], 4, sample=False)
    assert forecast.state_mean.shape == (batch, 4, S) and warm.state_mean.shape == (batch, 4, S)
    again, _ = model.forecast(window.states[:, :5], window.actions[:, :8], 4, sample=False)
    torch.testing.assert_close(again.state_mean, forecast.state_mean)


def test_rwm_sequence_kernel_equals_stepping() -> None:
    model = tiny("rwm", ensemble_size=2).eval()
    window = random_window(3, 7)
    member = torch.tensor([0, 1, 1])
    hidden, seq = model.observe(model.initial_hidden(3), window.states, window.actions, member)
    stepped, h = [], model.initial_hidden(3)
    for t in range(7):
        h, p = model.step(h, window.states[:, t], window.actions[:, t], member)
        stepped.append(p)
    torch.testing.assert_close(Prediction.stack(stepped).state_mean, seq.state_mean)
    torch.testing.assert_close(Prediction.stack(stepped).termination_logit, seq.termination_logit)
    for a, b in zip(h, hidden):
        torch.testing.assert_close(a, b)


def test_fused_inference_step_equals_the_autograd_step_across_row_blocks(monkeypatch) -> None:
    """`RWM.step` without autograd runs `gru_step`'s fused cell, in row blocks on the CPU: the same hidden states and
    predictions as `nn.GRU` (the autograd path), for 2 layers and a batch that spans uneven blocks."""
    monkeypatch.setattr(gru_step_module, "ROWS_PER_BLOCK", 4)
    model = tiny("rwm", ensemble_size=2, num_layers=2).eval()
    window = random_window(11, 5)
    member = torch.arange(11) % 2
    h_grad = h_fused = model.initial_hidden(11)
    for t in range(5):
        h_grad, p_grad = model.step(h_grad, window.states[:, t], window.actions[:, t], member)
        with torch.no_grad():
            h_fused, p_fused = model.step(h_fused, window.states[:, t], window.actions[:, t], member)
        assert p_grad.state_mean.requires_grad and not p_fused.state_mean.requires_grad
        torch.testing.assert_close(p_fused.state_mean, p_grad.state_mean.detach())
        torch.testing.assert_close(p_fused.contact_logits, p_grad.contact_logits.detach())
        for a, b in zip(h_fused, h_grad):
            assert a.shape == (11, 2, 16)
            torch.testing.assert_close(a, b.detach())
    assert not torch.equal(h_fused[0][:, 0], h_fused[0][:, 1])  # the layers are kept apart, not copied


def test_bfloat16_products_stay_close_to_float32_and_keep_the_hidden_state_float32(monkeypatch) -> None:
    """`set_step_matmul_dtype(torch.bfloat16)`: the products are rounded, nothing else; the step is close to fp32
    (bf16 has an 8-bit mantissa) but not equal, and the weights themselves are untouched."""
    monkeypatch.setattr(gru_step_module, "ROWS_PER_BLOCK", 4)
    model = tiny("rwm", ensemble_size=2, num_layers=2).eval()
    window = random_window(11, 5)
    member = torch.arange(11) % 2
    h32 = h16 = model.initial_hidden(11)
    with torch.no_grad():
        for t in range(5):
            model.set_step_matmul_dtype(None)
            h32, p32 = model.step(h32, window.states[:, t], window.actions[:, t], member)
            model.set_step_matmul_dtype(torch.bfloat16)
            h16, p16 = model.step(h16, window.states[:, t], window.actions[:, t], member)
            assert h16[0].dtype == p16.state_mean.dtype == torch.float32
            torch.testing.assert_close(p16.state_mean, p32.state_mean, atol=0.05, rtol=0.05)
    assert not torch.equal(p16.state_mean, p32.state_mean)
    assert model.state_gru.weight_ih_l0.dtype == torch.float32


@pytest.mark.parametrize("already", [0, 2])
@pytest.mark.parametrize("rows", [4, 9])
def test_transformer_causal_pass_equals_stepping(already: int, rows: int) -> None:
    """observe over T steps (one causal pass while the tokens fit in the context of 6, then per step) == T steps,
    from an empty or a partly filled context, in training mode (gradients) and with a trained distance bias."""
    model = tiny("transformer", ensemble_size=2).train()
    with torch.no_grad():
        model.distance_bias.normal_()
    window = random_window(3, already + rows)
    member = torch.tensor([0, 1, 1])
    start = model.initial_hidden(3)
    for t in range(already):
        start, _ = model.step(start, window.states[:, t], window.actions[:, t], member)
    states, actions = window.states[:, already:], window.actions[:, already:]
    hidden, seq = model.observe(start, states, actions, member)
    stepped, h = [], start
    for t in range(rows):
        h, p = model.step(h, states[:, t], actions[:, t], member)
        stepped.append(p)
    stepped = Prediction.stack(stepped)
    for name in ("state_mean", "state_std", "contact_logits", "foot_height", "termination_logit"):
        torch.testing.assert_close(getattr(seq, name), getattr(stepped, name))
    for a, b in zip(h, hidden, strict=True):
        torch.testing.assert_close(a, b)
    seq.state_mean.sum().backward()
    assert model.distance_bias.grad.abs().sum() > 0
    with torch.no_grad():  # inference (PyTorch's encoder fast path would give NaNs with the float mask)
        _, inferred = model.eval().observe(start, states, actions, member)
    torch.testing.assert_close(inferred.state_mean, seq.state_mean)


class ShiftModel(WorldModel):
    """Predicts state + 1 with zero spread and records every state it is fed."""

    def __init__(self) -> None:
        super().__init__(ModelConfig("no_change", S, A, C, F))
        self.inputs: list[torch.Tensor] = []

    def initial_hidden(self, batch_size, device=None):
        return ()

    def step(self, hidden, state, action, member=None, next_state=None):
        self.inputs.append(state.clone())
        zeros = state.new_zeros(state.shape[0])
        return (), Prediction(
            state + 1,
            torch.zeros_like(state),
            state.new_zeros(len(state), C),
            state.new_zeros(len(state), F),
            zeros,
            zeros,
        )


def test_forecast_feeds_back_its_own_predictions_not_the_truth() -> None:
    model = ShiftModel()
    true = torch.zeros(2, 12, S)  # the truth never moves; the model says +1 per step
    forecast, _ = model.forecast(true[:, :8], torch.zeros(2, 11, A), 4, sample=True)
    fed = model.inputs[-4:]  # inputs of the 4 forecast steps: the last true state, then the own predictions
    for k in range(4):
        torch.testing.assert_close(fed[k], torch.full_like(fed[k], float(k)))
    torch.testing.assert_close(forecast.state_mean[:, -1], torch.full((2, S), 4.0))  # teacher forcing would give 1


def test_training_loss_feeds_back_reparameterised_samples(monkeypatch) -> None:
    """Spy on a real RWM inside the training loss: forecast step k>0 gets the sample drawn from step k-1's
    prediction (a tensor in the autograd graph), never the true state of that row."""
    model = tiny("rwm").train()
    config = TrainConfig(history=5, forecast=4)
    window = random_window(3, 9)
    samples, inputs = [], []
    original_sample, original_step = Prediction.sample, model.step

    def spy_sample(self):
        samples.append(original_sample(self))
        return samples[-1]

    def spy_step(hidden, state, action, member=None, next_state=None):
        inputs.append(state)
        return original_step(hidden, state, action, member, next_state)

    monkeypatch.setattr(Prediction, "sample", spy_sample)
    monkeypatch.setattr(model, "step", spy_step)
    loss, parts = window_loss(model, window, config, pos_weight=1.0)
    assert len(inputs) == 4  # warm-up runs as one sequence; then one step per forecast row
    torch.testing.assert_close(inputs[0], window.states[:, 4])  # the last true history row
    for k in range(1, 4):
        assert inputs[k] is samples[k - 1] and inputs[k].requires_grad
        assert not torch.allclose(inputs[k], window.states[:, 4 + k])
    loss.backward()
    assert set(parts) == {"state", "contact", "foot", "termination", "bound"}
    assert all(p.grad is not None for p in model.parameters())


def test_state_constraints_keep_gravity_unit_and_joints_in_their_ranges(tmp_path) -> None:
    """Switched on, the predicted mean's projected gravity is a unit vector in physical units and its joint positions
    sit inside the MJCF ranges, for inputs far outside the data; the clamp lets gradients through; a checkpoint
    carries the switches and the limits; off, nothing changes."""
    from rwm_gym.model.checkpoint import load_checkpoint, save_checkpoint
    from rwm_gym.model.constraints import joint_ranges
    from rwm_gym.model.normalization import Normalizer

    normalizer, slices = Normalizer.from_spec(SPEC), SPEC.state_slices
    low, high = (
        torch.as_tensor(r - torch.tensor(SPEC.actuator.default_pose).numpy(), dtype=torch.float32)
        for r in joint_ranges(SPEC)
    )
    assert torch.isfinite(low).all() and (low < 0).all() and (high > 0).all()
    with pytest.raises(ValueError, match="spec"):
        build_model(model_config_for("rwm", SPEC, **TINY, unit_gravity=True))
    torch.manual_seed(0)
    model = build_model(model_config_for("rwm", SPEC, **TINY, unit_gravity=True, joint_limits=True), SPEC)
    state = (torch.randn(64, S) * 50).requires_grad_()
    _, p = model.step(model.initial_hidden(64), state, torch.rand(64, A) * 2 - 1)
    physical = normalizer.denormalize_state(p.state_mean)
    torch.testing.assert_close(physical[:, slices["projected_gravity"]].norm(dim=-1), torch.ones(64))
    joints = physical[:, slices["joint_pos"]]
    assert (joints >= low - 1e-4).all() and (joints <= high + 1e-4).all()
    assert ((joints - low).abs() < 1e-4).any() or ((joints - high).abs() < 1e-4).any()  # some were clamped
    p.state_mean[:, slices["joint_pos"]].sum().backward()
    assert (state.grad[:, slices["joint_pos"]] != 0).all()  # straight through: the residual's input still learns
    path = save_checkpoint(tmp_path / "m.safetensors", model, SPEC)
    loaded, meta = load_checkpoint(path)
    assert meta.model_config.unit_gravity and meta.model_config.joint_limits
    _, again = loaded.step(loaded.initial_hidden(64), state.detach(), torch.zeros(64, A))
    _, before = model.step(model.initial_hidden(64), state.detach(), torch.zeros(64, A))
    torch.testing.assert_close(again.state_mean, before.state_mean)
    torch.manual_seed(0)
    plain = build_model(model_config_for("rwm", SPEC, **TINY), SPEC)
    _, free = plain.step(plain.initial_hidden(64), state.detach(), torch.zeros(64, A))
    gravity = normalizer.denormalize_state(free.state_mean)[:, slices["projected_gravity"]].norm(dim=-1)
    assert not torch.allclose(gravity, torch.ones(64))


@pytest.mark.parametrize("kind", [k for k in MODEL_KINDS if k != "no_change"])
def test_own_heads_alone_predict_exactly_what_the_full_ensemble_predicts(kind: str) -> None:
    """Without the disagreement each rollout runs only its own head: the full ensemble's selection, up to the last
    float32 bit (a matmul kernel may round differently for a different row count)."""
    model = tiny(kind, ensemble_size=3).eval()
    batch = 7
    window = random_window(batch, 2)
    member = torch.tensor([2, 0, 1, 1, 2, 0, 2])
    hidden = model.initial_hidden(batch)
    with torch.no_grad():
        _, full = model.step(hidden, window.states[:, 0], window.actions[:, 0], member)
        with model.computing_disagreement(False):
            _, own = model.step(hidden, window.states[:, 0], window.actions[:, 0], member)
            _, mixture = model.step(hidden, window.states[:, 0], window.actions[:, 0])  # no member: all heads
        _, after = model.step(hidden, window.states[:, 0], window.actions[:, 0], member)
    for name in ("state_mean", "state_std", "contact_logits", "foot_height", "termination_logit"):
        torch.testing.assert_close(getattr(own, name), getattr(full, name), rtol=1e-6, atol=1e-6, msg=name)
    assert own.uncertainty is None and (full.uncertainty > 0).all()
    assert mixture.uncertainty is not None  # a mixture needs every head anyway
    assert after.uncertainty is not None  # the block restores the setting


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_warm_hidden_is_the_hidden_state_of_warm_up(kind: str) -> None:
    model = tiny(kind, ensemble_size=2).eval()
    window = random_window(3, 6)
    member = torch.tensor([0, 1, 1])
    with torch.no_grad():
        expected, _ = model.warm_up(window.states, window.actions, member)
        hidden = model.warm_hidden(window.states, window.actions, member)
    assert len(hidden) == len(expected)
    for h, e in zip(hidden, expected):
        assert torch.equal(h, e)


def test_log_std_band_penalty_never_inverts_the_band() -> None:
    """Descending on the band penalty alone (what the mse loss leaves of it) narrows the band to zero width and no
    further: an inverted band (max below min) earns nothing."""
    model = tiny("rwm")
    head = model.heads.state
    optimizer = torch.optim.SGD([head.min_log_std, head.max_log_std], lr=0.05)
    for _ in range(400):
        optimizer.zero_grad()
        model.regularization().backward()
        optimizer.step()
    width = (head.max_log_std - head.min_log_std).detach()
    assert width.min() > -0.1, width.min()
    assert float(model.regularization().detach()) >= 0.0
