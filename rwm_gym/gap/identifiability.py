"""Which effects the measured data could reveal at all: each effect's signal on these windows against the noise floor.

A walking policy's log is regular: it may never reach the torque limit, reverse a joint slowly, or change targets
fast. Whether an effect is identifiable from a given log is a property of the log, so it is measured on the log
itself: every effect at its realistic default magnitude (`Parameter.default`) is re-simulated on the held-out windows,
and its signal is the gap it would open against the nominal re-simulation (the same normalised MSE over
`GAP_HORIZONS`). An effect whose signal is below `SIGNAL_TO_FLOOR` times the sensor-noise floor would leave a gap
the floor test cannot tell from noise, so it needs data that excites it (`make-measured --policy excitation`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import gap_per_window
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.physics.params import PhysicsParams

SIGNAL_TO_FLOOR = 1.0
"""An effect at its default magnitude must open a gap of at least this multiple of the floor to be identifiable."""


def identifiability(
    effects: dict[str, Effect],
    resim: Resimulator,
    windows: Windows,
    base: PhysicsParams,
    nominal: np.ndarray,
    floor: float,
) -> dict[str, dict]:
    """{effect: {magnitude, signal, signal_to_floor, identifiable}} on `windows`; `nominal` (W, H, S) is the base
    simulator's re-simulation of them and `floor` the mean noise floor."""
    reference = dataclasses.replace(windows, target=nominal)
    out = {}
    for name, effect in effects.items():
        values = np.array([p.default for p in effect.parameters])
        try:
            signal = float(
                gap_per_window(resim.spec, resim.rollout(windows, effect.physics(values, base)), reference).mean()
            )
        except SimulationDiverged as err:
            out[name] = {
                "magnitude": values.tolist(),
                "signal": float("nan"),
                "signal_to_floor": float("nan"),
                "identifiable": False,
                "reason": f"simulation blows up: {err.reason}",
            }
            continue
        ratio = signal / floor
        out[name] = {
            "magnitude": values.tolist(),
            "signal": signal,
            "signal_to_floor": ratio,
            "identifiable": bool(ratio >= SIGNAL_TO_FLOOR),
        }
    return out
