"""Keeps the paper's ratio of one update per `env_steps_per_update` environment steps.

The system's step count comes from the replay (frames received in total). A
replay that restarts counts from zero again, so the clock adds up increments
instead of trusting the absolute number; it survives learner restarts through
its state in the checkpoint. (A replay that restarted and has already passed its
old count while the learner was down cannot be told apart from one that kept
running; its extra steps are then counted twice.)
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class StepClock:
    env_steps: int = 0  # environment steps of the whole system since the run began
    last_reported: int | None = None  # the replay's counter when last seen
    steps_at_first_update: int | None = None

    def observe(self, replay_env_steps_total: int) -> None:
        """Takes the replay's global counter; a drop means the replay restarted from zero."""
        if self.last_reported is None:
            increment = 0 if self.env_steps else replay_env_steps_total
        elif replay_env_steps_total >= self.last_reported:
            increment = replay_env_steps_total - self.last_reported
        else:
            increment = replay_env_steps_total
        self.env_steps += increment
        self.last_reported = replay_env_steps_total

    def start_updates(self) -> None:
        if self.steps_at_first_update is None:
            self.steps_at_first_update = self.env_steps

    def updates_due(self, env_steps_per_update: float) -> float:
        """How many updates the steps seen since updates began pay for."""
        if self.steps_at_first_update is None:
            return 0.0
        return (self.env_steps - self.steps_at_first_update) / env_steps_per_update

    def may_update(self, updates_done: int, env_steps_per_update: float, tolerance: float) -> bool:
        """True unless the learner is more than `tolerance` (a share, at least one update) ahead."""
        if self.steps_at_first_update is None:
            return False
        due = self.updates_due(env_steps_per_update)
        return updates_done < due + max(1.0, tolerance * due)

    def state_dict(self) -> dict:
        # The replay's counter is kept so that steps taken while the learner was down still count
        # when the same replay is still running; a restarted replay shows as a drop (see observe).
        return {"env_steps": self.env_steps, "last_reported": self.last_reported,
                "steps_at_first_update": self.steps_at_first_update}

    def load_state_dict(self, state: dict) -> None:
        self.env_steps = int(state["env_steps"])
        last, first = state.get("last_reported"), state.get("steps_at_first_update")
        self.last_reported = None if last is None else int(last)
        self.steps_at_first_update = None if first is None else int(first)
