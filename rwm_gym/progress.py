"""One progress bar for a run budgeted in steps and/or wall-clock minutes (`train`, `ppo`, `mbpo`).

A bar whose total is not what the run will do misleads: with a step budget it counts the steps the run will really
take (the caller rounds up to whole rollouts, say); with only a time budget it counts seconds out of the budget, and
the steps go in its postfix. Neither ever passes its total.
"""

from __future__ import annotations

import math

from tqdm import tqdm


def whole_rollouts(steps: int, rollout: int) -> int:
    """Steps a learner that stops only between rollouts of `rollout` steps takes to reach `steps` (SB3's `learn`)."""
    return math.ceil(steps / rollout) * rollout


class BudgetBar:
    """tqdm bar over `steps` (when given) or else over `minutes` in seconds; `show(steps_done, seconds)` moves it.

    Both arguments of `show` are totals since the bar's start (absolute, not increments); the bar stops at its total.
    """

    def __init__(
        self,
        *,
        steps: int | None,
        minutes: float | None,
        desc: str,
        unit: str = "step",
        initial: int = 0,
        disable: bool = False,
        unit_scale: bool = False,
    ):
        if not steps and not minutes:
            raise ValueError("BudgetBar needs a budget: steps and/or minutes")
        self.by_time = not steps
        self.unit = unit
        self.postfix: dict = {}
        self.seconds = 60 * minutes if minutes else None
        if self.by_time:
            self.total = max(1, math.ceil(self.seconds))
            self.bar = tqdm(
                total=self.total,
                desc=desc,
                unit="s",
                disable=disable,
                dynamic_ncols=True,
                bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} s of the budget [{elapsed}{postfix}]",
            )
        else:
            self.total = int(steps)
            self.bar = tqdm(
                total=self.total,
                initial=min(initial, self.total),
                desc=desc,
                unit=unit,
                unit_scale=unit_scale,
                disable=disable,
                dynamic_ncols=True,
            )

    def show(self, steps_done: int, seconds: float, **postfix) -> None:
        """Move the bar to `steps_done` (step budget) or `seconds` (time budget), capped at the total."""
        if self.bar.disable:
            return
        if self.by_time:  # a run that stopped on its clock fills its bar, whatever the rounding
            target = self.total if seconds >= self.seconds else min(int(seconds), self.total)
        else:
            target = min(int(steps_done), self.total)
        if target > self.bar.n:
            self.bar.update(target - self.bar.n)
        self.postfix.update(postfix)
        if self.by_time:
            self.postfix[self.unit + "s"] = f"{steps_done:,}"
        if self.postfix:
            self.bar.set_postfix(self.postfix, refresh=False)

    def close(self) -> None:
        self.bar.close()
