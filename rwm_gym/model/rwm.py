"""The Robotic World Model (Li, Krause, Hutter, arXiv 2501.10100): two GRUs over (normalised state, action).

One GRU feeds the Gaussian state head (a residual on the last state, log-std softly bounded between learned limits,
optionally an ensemble of k heads); the other feeds the privileged head (contact logits, foot heights, termination
logit), so the rarely-needed privileged targets do not compete with the state for the recurrent capacity.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.func import functional_call

from rwm_gym.model.base import Hidden, Prediction, WorldModel
from rwm_gym.model.config import ModelConfig
from rwm_gym.model.gru_step import gru_step, layer_weights
from rwm_gym.model.heads import Heads


class RWM(WorldModel):
    """Hidden = (state GRU, privileged GRU), each (B, num_layers, hidden_size): batch first, unlike `nn.GRU`."""

    warm_hidden_reads_member = False  # the GRUs read states and actions only; the heads come after them
    fused_step = True
    """`step` without autograd runs `gru_step`'s fused cell (off: `nn.GRU`, as `benchmarks/imagination.py` compares)."""
    step_matmul_dtype: torch.dtype | None = None
    """dtype of the fused cell's products (None: the weights' own; `torch.bfloat16`: `set_step_matmul_dtype`)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config)
        inputs = config.state_dim + config.action_dim
        self.state_gru = nn.GRU(inputs, config.hidden_size, config.num_layers, batch_first=True)
        self.privileged_gru = nn.GRU(inputs, config.hidden_size, config.num_layers, batch_first=True)
        self.heads = Heads(config.hidden_size, config.hidden_size, config)
        # Parameterless one-layer GRUs (meta device: no memory, no RNG draws) that run one layer of a stacked GRU
        # with its weights, so the hidden state of every layer at every step can be kept (a tuple: not submodules).
        self._one_layer = tuple(
            nn.GRU(inputs if layer == 0 else config.hidden_size, config.hidden_size, 1, batch_first=True, device="meta")
            for layer in range(config.num_layers)
        )

    def initial_hidden(self, batch_size: int, device: torch.device | str | None = None) -> Hidden:
        shape = (batch_size, self.config.num_layers, self.config.hidden_size)
        device = self.device if device is None else device
        return torch.zeros(shape, device=device), torch.zeros(shape, device=device)

    def observe(
        self,
        hidden: Hidden,
        states: torch.Tensor,
        actions: torch.Tensor,
        member: torch.Tensor | None = None,
        next_states: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        """Both GRUs over the whole sequence at once (cuDNN on GPU); `next_states` is not used."""
        (out_state, out_privileged), hidden = self._recur(hidden, states, actions)
        return hidden, self.heads(out_state, out_privileged, states, member)

    def _recur(
        self, hidden: Hidden, states: torch.Tensor, actions: torch.Tensor
    ) -> tuple[tuple[torch.Tensor, torch.Tensor], Hidden]:
        """Both GRUs over (states, actions) (B, T, .): their outputs (B, T, H) and the hidden state after T steps."""
        x = torch.cat([states, actions], dim=-1)
        h_state, h_privileged = (h.transpose(0, 1).contiguous() for h in hidden)
        out_state, h_state = self.state_gru(x, h_state)
        out_privileged, h_privileged = self.privileged_gru(x, h_privileged)
        return (out_state, out_privileged), (h_state.transpose(0, 1), h_privileged.transpose(0, 1))

    def warm_hidden(self, states: torch.Tensor, actions: torch.Tensor, member: torch.Tensor | None = None) -> Hidden:
        """The GRUs over the history without the heads (the hidden state does not read them)."""
        batch, history = states.shape[:2]
        hidden = self.initial_hidden(batch, states.device)
        if history == 1:
            return hidden
        return self._recur(hidden, states[:, :-1], actions[:, : history - 1])[1]

    def step(
        self,
        hidden: Hidden,
        state: torch.Tensor,
        action: torch.Tensor,
        member: torch.Tensor | None = None,
        next_state: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        """Without autograd (imagination, forecasts under no_grad) the GRUs run `gru_step`'s fused cell; with it,
        `nn.GRU` (the same numbers to float rounding)."""
        if torch.is_grad_enabled() or not self.fused_step:
            hidden, prediction = self.observe(hidden, state.unsqueeze(1), action.unsqueeze(1), member)
            return hidden, prediction.map(lambda t: t.squeeze(1))
        x = torch.cat([state, action], dim=-1)
        state_weights, privileged_weights = self._fused_weights()
        hidden = (
            gru_step(self.state_gru, x, hidden[0], state_weights),
            gru_step(self.privileged_gru, x, hidden[1], privileged_weights),
        )
        return hidden, self.heads(hidden[0][:, -1], hidden[1][:, -1], state, member)

    def set_step_matmul_dtype(self, dtype: torch.dtype | None) -> None:
        """Run the fused cell's products in `dtype` (e.g. `torch.bfloat16`); the hidden state, the gates and the heads
        stay in the weights' dtype. Training and `observe` are unaffected."""
        self.step_matmul_dtype = dtype

    def _fused_weights(self) -> tuple[list, list]:
        """Both GRUs' `layer_weights`, rebuilt only when a weight changed (an optimiser step, a move, a load)."""
        grus = (self.state_gru, self.privileged_gru)
        key = (self.step_matmul_dtype, *((p.data_ptr(), p._version) for gru in grus for p in gru.parameters()))
        cached = self.__dict__.get("_fused_cache")
        if cached is None or cached[0] != key:
            cached = (key, tuple(layer_weights(gru, self.step_matmul_dtype) for gru in grus))
            self.__dict__["_fused_cache"] = cached
        return cached[1]

    def _layer_by_layer(self, gru: nn.GRU, x: torch.Tensor, hidden: torch.Tensor) -> torch.Tensor:
        """Every layer's hidden state after every step: x (B, T, in), hidden (B, L, H) -> (B, T, L, H). Same kernel
        and numbers as the stacked call (which also runs layer after layer over the whole sequence)."""
        layers = []
        for layer, template in enumerate(self._one_layer):
            weights = {
                f"{name}_l0": getattr(gru, f"{name}_l{layer}")
                for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh")
            }
            x, _ = functional_call(template, weights, (x, hidden[:, layer].unsqueeze(0).contiguous()))
            layers.append(x)
        return torch.stack(layers, dim=2)

    def hidden_trajectory(
        self,
        hidden: Hidden,
        states: torch.Tensor,
        actions: torch.Tensor,
        member: torch.Tensor | None = None,
        next_states: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        """One sequence pass per layer of both GRUs; the predictions are forecasts (`next_states` is not used)."""
        x = torch.cat([states, actions], dim=-1)
        h_state = self._layer_by_layer(self.state_gru, x, hidden[0])
        h_privileged = self._layer_by_layer(self.privileged_gru, x, hidden[1])
        prediction = self.heads(h_state[:, :, -1], h_privileged[:, :, -1], states, member)
        return (h_state, h_privileged), prediction
