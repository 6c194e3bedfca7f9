"""Re-simulation of measured data: start a simulator at measured states, drive it with the measured actions.

A `Windows` holds many short stretches of measured episodes; `Resimulator.rollout` runs all of them at once on
`mujoco.batch` and returns the simulated states, so the residual simulated - measured can be taken per channel, step
and window. Each window first replays `warmup` measured steps (state overwritten with the measured one after each), so
state that is not in qpos/qvel holds what the robot's did when the window starts: the actuator's delay buffer the
measured commands, and the solver's warm start (`qacc_warmstart`, the last step's accelerations) those of the measured
motion. The second matters for a solver stopped after a few iterations (the fast MJCF's 4): its solution depends on
where it starts, and at a touchdown a wrong start is not forgotten (`WARMUP`).

A candidate parameter can make MuJoCo's integration blow up; MuJoCo then counts a warning in `mjData.warning`, prints
it once and resets the simulation, which would pass unnoticed as a plausible state. `rollout` reads the batch's warning
counters (and checks the states are finite) and raises `SimulationDiverged` with the reason, so the fit can reject the
parameters and say why; MuJoCo's own print is held back meanwhile (the reason carries it).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import mujoco
import numpy as np

from rwm_gym.data.dataset import Dataset
from rwm_gym.physics.params import CONVERGED_SOLVER, ModelCache, PhysicsParams, SolverSettings, drive_rewrites
from rwm_gym.physics.robot import RobotLayout, measure
from rwm_gym.physics.sensors import SensorBias
from rwm_gym.physics.simulator import DIVERGENCE_WARNINGS, BatchSimulator
from rwm_gym.spec import TaskSpec


@contextmanager
def held_warnings() -> Iterator[None]:
    """MuJoCo's warning messages of the block are dropped instead of printed to stdout and MUJOCO_LOG.TXT (the warning
    counters in mjData count as before, and `check_diverged` reports from them); the handler before is restored."""
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: None)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


class SimulationDiverged(RuntimeError):
    """A re-simulation blew up in some windows; `reason` says how, `windows` (W,) marks them."""

    def __init__(self, reason: str, windows: np.ndarray):
        super().__init__(reason)
        self.reason, self.windows = reason, windows


WARMUP = 2
"""Measured steps replayed before each window by default. On noise-free data of the fast MJCF's own physics, 2 leave 2
windows in 94 tens of N·m off at the true parameters (a warm start still off the robot's at a touchdown), 4 none; but
each replayed step is a row no window can start at, and on episodes a robot falls in within a second 4 left too few
held-out blocks for a significant fit (`GapConfig.warmup` sets it)."""

RECENT_ROLLOUTS = 32
"""Re-simulations a `Resimulator` keeps to hand out again (the workflow asks for the nominal one of the same windows
several times, and a search for the point it evaluated last)."""

RECENT_BYTES = 256 * 2**20
"""Memory the kept re-simulations may take; the oldest are dropped first."""

WINDOW_ARRAYS = ("episode", "start", "qpos", "qvel", "actions", "state0", "target", "contact0")


@dataclass(frozen=True)
class Windows:
    """W measured windows of `horizon` transitions, each preceded by `warmup` replayed transitions."""

    episode: np.ndarray
    """(W,) episode index in the dataset."""
    start: np.ndarray
    """(W,) row (within the episode) where the re-simulation starts."""
    qpos: np.ndarray
    """(W, K+1, nq) measured qpos at rows start-K .. start."""
    qvel: np.ndarray
    """(W, K+1, nv) measured qvel at the same rows."""
    actions: np.ndarray
    """(W, K+H, A) measured actions at rows start-K .. start+H-1."""
    state0: np.ndarray
    """(W, S) measured state at row start."""
    target: np.ndarray
    """(W, H, S) measured state at rows start+1 .. start+H."""
    contact0: np.ndarray
    """(W, C) measured contact flags at row start."""
    horizon: int
    warmup: int
    gap_ceiling: np.ndarray | None = None
    """(len(gap_horizons(horizon)),) the most one window's gap counts at each gap horizon (`fit.gap_ceiling`);
    None: uncapped."""

    def __len__(self) -> int:
        return len(self.start)

    def join(self, other: Windows) -> Windows:
        """These windows followed by `other`'s (same horizon and warm-up)."""
        if (other.horizon, other.warmup) != (self.horizon, self.warmup):
            raise ValueError(
                f"cannot join windows of horizon/warm-up {self.horizon}/{self.warmup} and "
                f"{other.horizon}/{other.warmup}"
            )
        take = {k: np.concatenate([getattr(self, k), getattr(other, k)]) for k in WINDOW_ARRAYS}
        ceilings = (self.gap_ceiling, other.gap_ceiling)
        ceiling = None if any(c is None for c in ceilings) else np.maximum(*ceilings)
        return Windows(**take, horizon=self.horizon, warmup=self.warmup, gap_ceiling=ceiling)

    def subset(self, mask: np.ndarray) -> Windows:
        """The windows where `mask` (W,) holds."""
        take = {k: getattr(self, k)[mask] for k in WINDOW_ARRAYS}
        return Windows(**take, horizon=self.horizon, warmup=self.warmup, gap_ceiling=self.gap_ceiling)

    def every(self, stride: int) -> Windows:
        """Every `stride`-th window, from the first (all of them at 1)."""
        return self if stride == 1 else self.subset(np.arange(len(self)) % stride == 0)


def make_windows(dataset: Dataset, episodes: np.ndarray, horizon: int, stride: int, warmup: int = WARMUP) -> Windows:
    """Every `stride`-th window of `horizon` transitions in the given episodes (none crosses an episode's end)."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in WINDOW_ARRAYS}
    for e in np.asarray(episodes, int):
        ep = dataset.episode(int(e))
        rows = len(ep["state"])
        starts = np.arange(warmup, rows - horizon, stride)
        if len(starts) == 0:
            continue
        back = starts[:, None] + np.arange(-warmup, 1)[None]
        ahead = starts[:, None] + np.arange(1, horizon + 1)[None]
        acts = starts[:, None] + np.arange(-warmup, horizon)[None]
        parts["episode"].append(np.full(len(starts), e))
        parts["start"].append(starts)
        parts["qpos"].append(ep["qpos"][back])
        parts["qvel"].append(ep["qvel"][back])
        parts["actions"].append(ep["action"][acts].astype(np.float64))
        parts["state0"].append(ep["state"][starts])
        parts["target"].append(ep["state"][ahead])
        parts["contact0"].append(ep["contact"][starts])
    if not parts["start"]:
        raise ValueError(f"{dataset.path}: no episode is longer than {warmup + horizon} rows (needed for windows)")
    return Windows(**{k: np.concatenate(v) for k, v in parts.items()}, horizon=horizon, warmup=warmup)


class Resimulator:
    """Re-simulates windows of measured data on one robot model (the task spec's or `xml_file`).

    `solver` (default `CONVERGED_SOLVER`): every physics step solved to convergence, whatever the MJCF's iteration
    count. With a few iterations per step (the fast MJCF for PPO) the solve is left unfinished and carried to the next
    step, so a re-simulated window is a rough function of the parameters and of the (noisy) measured start state, and
    a fit of a constraint-borne effect (joint friction, contacts) lands off the true value.
    """

    def __init__(
        self,
        spec: TaskSpec,
        xml_file: str | Path | None = None,
        nthread: int = 0,
        solver: SolverSettings | None = CONVERGED_SOLVER,
    ):
        self.spec, self.xml_file, self.nthread, self.solver = spec, xml_file, nthread, solver
        self.models = ModelCache(spec, xml_file, solver)
        self._recent: OrderedDict[tuple, tuple[Windows, dict[str, np.ndarray]]] = OrderedDict()

    def model(self, params: PhysicsParams) -> mujoco.MjModel:
        """`build_model(spec, xml_file, params, solver)`, from a once-compiled structure (`ModelCache`)."""
        return self.models(params)

    def rollout(
        self,
        windows: Windows,
        params: PhysicsParams,
        horizon: int | None = None,
        correction: TorqueCorrection | None = None,
    ) -> np.ndarray:
        """Simulated states (W, H, S) at rows start+1 .. start+H of every window (H = horizon, default all)."""
        return self.simulate(windows, params, horizon, correction)["state"]

    def simulate(
        self,
        windows: Windows,
        params: PhysicsParams,
        horizon: int | None = None,
        correction: TorqueCorrection | None = None,
    ) -> dict[str, np.ndarray]:
        """`rollout` with the raw arrays too: {"state" (W, H, S), "qpos" (W, H, nq), "qvel" (W, H, nv),
        "joint_torque" (W, H, A), "contact" (W, H, C) bool}, all as the sensors read them (the measured rows are
        readings: a sensor bias of `params` is undone on each before the simulation takes it,
        `rwm_gym.physics.sensors`); `correction` adds a learned joint torque at every policy step.

        A simulation is deterministic: the `RECENT_ROLLOUTS` last ones without a correction are kept and handed out
        again (as copies) for the same windows object, parameters and horizon."""
        horizon = horizon or windows.horizon
        if correction is not None or not _hashable(params):
            return self._simulate(windows, params, horizon, correction)
        key = (id(windows), params, horizon)
        kept = self._recent.get(key)
        if kept is None or kept[0] is not windows:
            kept = (windows, self._simulate(windows, params, horizon, None))
            self._recent[key] = kept
            while len(self._recent) > RECENT_ROLLOUTS or _bytes(self._recent) > RECENT_BYTES:
                self._recent.popitem(last=False)
        if key in self._recent:
            self._recent.move_to_end(key)
        return {k: v.copy() for k, v in kept[1].items()}

    def _simulate(
        self, windows: Windows, params: PhysicsParams, horizon: int, correction: TorqueCorrection | None
    ) -> dict[str, np.ndarray]:
        """`simulate`, run."""
        spec = self.spec
        model = self.model(params)
        layout = RobotLayout.from_model(model, spec)
        keyframe = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, spec.keyframe)
        n, k = len(windows), windows.warmup
        sim = BatchSimulator(model, n, self.nthread, drive_rewrites(spec, model, params))
        bias = SensorBias.of(layout, params)

        def truth(i: int) -> tuple[np.ndarray, np.ndarray]:  # the state under the measured row start-K+i
            return (
                bias.unread(windows.qpos[:, i], windows.qvel[:, i])
                if bias
                else (windows.qpos[:, i], windows.qvel[:, i])
            )

        qpos, qvel = sim.batch.bind("qpos"), sim.batch.bind("qvel")
        applied = sim.batch.bind("qfrc_applied") if correction is not None else None
        ctrl = np.zeros((n, model.nu))
        act = spec.actuator
        default, scale = np.asarray(act.default_pose), act.action_scale
        if correction is not None:
            correction.start(n)

        def step(action: np.ndarray) -> None:
            target = default + scale * np.clip(action, -1.0, 1.0)
            if correction is not None:
                applied[:, layout.dof_adr] = correction.torque(
                    np.asarray(qpos)[:, layout.qpos_adr], np.asarray(qvel)[:, layout.dof_adr], target
                )
            ctrl[:, layout.actuator_ids] = target
            sim.step(ctrl, spec.substeps)

        sim.reset(np.arange(n), keyframe, *truth(0))
        warnings_before = np.array(sim.batch.warning[:, :, 1])
        out = {
            "state": np.empty((n, horizon, spec.state_dim)),
            "qpos": np.empty((n, horizon, model.nq)),
            "qvel": np.empty((n, horizon, model.nv)),
            "joint_torque": np.empty((n, horizon, spec.action_dim)),
            "contact": np.empty((n, horizon, spec.contact_dim), bool),
        }
        # A state written over needs no forward pass before the next step: mj_step computes everything it uses from
        # the state (qpos, qvel, controls, warm start), and the drive rewrites read qpos and qvel only.
        with held_warnings():
            for i in range(k):
                if i > 0:
                    qpos[:], qvel[:] = truth(i)
                step(windows.actions[:, i])
            if k > 0:
                qpos[:], qvel[:] = truth(k)
            for h in range(horizon):
                step(windows.actions[:, k + h])
                arrays = sim.arrays()
                if bias is not None:
                    read_qpos, read_qvel = bias.read(arrays["qpos"], arrays["qvel"])
                    arrays = {**arrays, "qpos": read_qpos, "qvel": read_qvel}
                measured = measure(layout, spec, **arrays)
                out["state"][:, h], out["contact"][:, h] = measured.state, measured.contact
                out["qpos"][:, h], out["qvel"][:, h] = arrays["qpos"], arrays["qvel"]
                out["joint_torque"][:, h] = arrays["actuator_force"][:, layout.actuator_ids]
        check_diverged(np.array(sim.batch.warning[:, :, 1]) - warnings_before, out["state"])
        return out


def _bytes(kept: OrderedDict[tuple, tuple[Windows, dict[str, np.ndarray]]]) -> int:
    return sum(a.nbytes for _, arrays in kept.values() for a in arrays.values())


def _hashable(params: PhysicsParams) -> bool:
    try:
        hash(params)
    except TypeError:
        return False
    return True


class TorqueCorrection(Protocol):
    """A learned joint torque added by `Resimulator.simulate` at every policy step (`rwm_gym.gap.learned`)."""

    def start(self, n: int) -> None:
        """Forget the history of n new simulations."""

    def torque(self, joint_pos: np.ndarray, joint_vel: np.ndarray, target: np.ndarray) -> np.ndarray:
        """(n, A) N·m from the current joint positions (rad), velocities (rad/s) and position targets (rad)."""


def check_diverged(new_warnings: np.ndarray, states: np.ndarray) -> None:
    """Raise `SimulationDiverged` if any simulation counted a divergence warning (new_warnings (W, mjNWARNING)) or
    produced a non-finite or huge state (W, H, S)."""
    warned = np.zeros(len(states), bool)
    reasons = []
    for code, text in DIVERGENCE_WARNINGS.items():
        hit = new_warnings[:, code] > 0
        if hit.any():
            reasons.append(f"MuJoCo warning '{text}' in {int(hit.sum())} of {len(hit)} windows")
            warned |= hit
    bad = ~np.isfinite(states).all(axis=(1, 2)) | (np.abs(np.nan_to_num(states)) > 1e6).any(axis=(1, 2))
    if bad.any():
        reasons.append(f"non-finite or huge state in {int(bad.sum())} of {len(bad)} windows")
    if reasons:
        raise SimulationDiverged("; ".join(reasons), warned | bad)


def normalised_residual(spec: TaskSpec, simulated: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """(simulated - measured) / the spec's state std, per channel; shapes (..., S)."""
    return (simulated - measured) / spec.state_std
