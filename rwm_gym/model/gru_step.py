"""One step of a stacked `nn.GRU` for inference, written out so the imagined env's step runs near matmul speed.

`nn.GRU` on one time step took 1.45x the time of its matrix products alone on the development CPU (4096 rows, one
thread: 116 against 80 ms for two layers; sequence set-up, layout copies, separate gate kernels). Here each layer is
three products and a few in-place gate operations, over blocks of rows small enough for the gate arithmetic to stay
in cache, written straight into the output. Same equations and weights as PyTorch's GRU (r, z, n gate order;
n = tanh(W_in x + b_in + r * (W_hn h + b_hn)); h' = n + z * (h - n)); no autograd: use it under `torch.no_grad()` /
`torch.inference_mode()` only.

With `matmul_dtype=torch.bfloat16` the products run in bfloat16 (fp32 accumulation in oneDNN; 2.5-4x the fp32 rate
on CPUs with AVX512-BF16 or AMX) while the gate arithmetic and the hidden state stay float32: only the products'
inputs and outputs are rounded (the effect on speed and forecasts: docs/results/time-to-walk.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

ROWS_PER_BLOCK = 1024
"""Rows per block on the CPU: 1024 x 768 gate floats (3 MB) stay in cache between the products and the gates (one
2-layer GRU of 256 on 4096 rows, one thread: 62.2 ms in blocks of 1024, 65.7 ms in one block; 512 and 2048 within
1 %; measured on the 2-core development machine). One block on a GPU."""


@dataclass(frozen=True)
class _LayerWeights:
    """One layer's weights in the layout the step multiplies by: the r and z gates take their input and hidden
    products summed in one output (the hidden product accumulates onto the input one, biases pre-added); n keeps its
    hidden product apart, since r scales it."""

    input_t: torch.Tensor  # (in, 3H): W_ih transposed
    hidden_rz_t: torch.Tensor  # (H, 2H): the r and z rows of W_hh, transposed
    hidden_n_t: torch.Tensor  # (H, H): the n rows of W_hh, transposed
    input_bias: torch.Tensor  # (3H,): b_ih, plus b_hh on r and z
    hidden_n_bias: torch.Tensor  # (H,): b_hn

    @classmethod
    def of(cls, gru: nn.GRU, layer: int, matmul_dtype: torch.dtype | None = None) -> _LayerWeights:
        """The layer's weights; with `matmul_dtype` the three products' matrices are copies in that dtype (the
        biases stay in the GRU's dtype)."""
        w_ih, w_hh = getattr(gru, f"weight_ih_l{layer}"), getattr(gru, f"weight_hh_l{layer}")
        b_ih, b_hh = getattr(gru, f"bias_ih_l{layer}"), getattr(gru, f"bias_hh_l{layer}")
        two = 2 * gru.hidden_size
        matrices = [w_ih.t(), w_hh[:two].t(), w_hh[two:].t()]
        if matmul_dtype is not None:
            matrices = [m.to(matmul_dtype).contiguous() for m in matrices]
        return cls(*matrices, torch.cat([b_ih[:two] + b_hh[:two], b_ih[two:]]), b_hh[two:])

    @property
    def low_precision(self) -> bool:
        return self.input_t.dtype != self.input_bias.dtype


def _layer(x: torch.Tensor, h: torch.Tensor, w: _LayerWeights, out: torch.Tensor) -> torch.Tensor:
    """The layer's new hidden state for a block of rows, written into `out` (rows, H)."""
    hidden = h.shape[1]
    gates = torch.addmm(w.input_bias, x, w.input_t)  # (rows, 3H): every input product
    reset_update = gates[:, : 2 * hidden].addmm_(h, w.hidden_rz_t).sigmoid_()  # BLAS accumulates: no extra pass
    candidate = torch.addmm(w.hidden_n_bias, h, w.hidden_n_t)
    return _new_hidden(gates[:, 2 * hidden :], reset_update, candidate, h, out)


def _layer_low_precision(x: torch.Tensor, h: torch.Tensor, w: _LayerWeights, out: torch.Tensor) -> torch.Tensor:
    """`_layer` with the products in the weights' (lower) dtype and everything else in the hidden state's."""
    hidden, low = h.shape[1], w.input_t.dtype
    h_low = h.to(low)
    gates = torch.mm(x.to(low), w.input_t).to(h.dtype).add_(w.input_bias)
    reset_update = gates[:, : 2 * hidden].add_(torch.mm(h_low, w.hidden_rz_t)).sigmoid_()
    candidate = torch.mm(h_low, w.hidden_n_t).to(h.dtype).add_(w.hidden_n_bias)
    return _new_hidden(gates[:, 2 * hidden :], reset_update, candidate, h, out)


def _new_hidden(
    input_n: torch.Tensor, reset_update: torch.Tensor, hidden_n: torch.Tensor, h: torch.Tensor, out: torch.Tensor
) -> torch.Tensor:
    """h' = n + z * (h - n) with n = tanh(input_n + r * hidden_n), written into `out` (hidden_n is overwritten)."""
    hidden = h.shape[1]
    candidate = torch.addcmul(input_n, reset_update[:, :hidden], hidden_n, out=hidden_n)
    candidate = candidate.mul_(2.0).sigmoid_().mul_(2.0).sub_(1.0)  # tanh(a) = 2 sigmoid(2a) - 1: 4x faster on CPU
    return torch.lerp(candidate, h, reset_update[:, hidden:], out=out)


def layer_weights(gru: nn.GRU, matmul_dtype: torch.dtype | None = None) -> list[_LayerWeights]:
    """Every layer's weights in `gru_step`'s layout (build once and pass as `weights=` to skip the per-call work)."""
    if gru.bidirectional or not gru.bias or gru.proj_size:
        raise ValueError("gru_step handles unidirectional GRUs with biases and no projection")
    return [_LayerWeights.of(gru, layer, matmul_dtype) for layer in range(gru.num_layers)]


def gru_step(
    gru: nn.GRU, x: torch.Tensor, hidden: torch.Tensor, weights: list[_LayerWeights] | None = None
) -> torch.Tensor:
    """x (B, in), hidden (B, L, H) batch first -> the hidden state after one step (B, L, H); its last layer is the
    GRU's output. Requires a unidirectional GRU with biases (what every model here builds). `weights`: the GRU's
    `layer_weights` (default: its own, built now, in its dtype)."""
    weights = weights if weights is not None else layer_weights(gru)
    out = torch.empty_like(hidden)
    rows = x.shape[0] if x.device.type != "cpu" else ROWS_PER_BLOCK
    for start in range(0, x.shape[0], rows):
        block = slice(start, start + rows)
        layer_input = x[block]
        for layer, w in enumerate(weights):
            step = _layer_low_precision if w.low_precision else _layer
            layer_input = step(layer_input, hidden[block, layer], w, out[block, layer])
    return out
