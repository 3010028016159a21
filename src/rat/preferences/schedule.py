"""When to ask for labels, and how many: exact budget accounting.

Rounds happen at ``first_step`` and then every ``every`` steps; each asks ``per_round`` queries
except the last, which is cut so that the queries asked add up to exactly ``budget``. A query
counts against the budget when it is asked, whether or not the teacher answers it (a skipping
teacher may decline), as in B-Pref.
"""

from __future__ import annotations

from dataclasses import dataclass

from rat.errors import RatError


@dataclass(frozen=True)
class FeedbackSchedule:
    """Query rounds over environment steps."""

    budget: int = 3000  #: total queries to ask
    first_step: int = 10_000  #: environment step of the first round
    every: int = 5_000  #: steps between later rounds
    per_round: int = 128  #: queries per round (the last one is cut to fit the budget)

    def __post_init__(self):
        if self.budget < 0:
            raise RatError(f"the label budget must not be negative, got {self.budget}")
        if self.every <= 0 or self.per_round <= 0 or self.first_step < 0:
            raise RatError("feedback every and per-round must be positive, and the first round step not negative")

    def queries_at(self, step: int, asked: int) -> int:
        """Queries to ask at environment ``step``, given ``asked`` so far (0 if no round is due)."""
        due = step == self.first_step or (step > self.first_step and (step - self.first_step) % self.every == 0)
        return min(self.per_round, self.budget - asked) if due else 0

    def rounds(self) -> list[tuple[int, int]]:
        """Every ``(step, queries)`` round until the budget is spent."""
        out, asked, step = [], 0, self.first_step
        while asked < self.budget:
            n = self.queries_at(step, asked)
            out.append((step, n))
            asked += n
            step += self.every
        return out

    def steps_needed(self) -> int:
        """The environment step of the round that spends the last of the budget."""
        rounds = self.rounds()
        return rounds[-1][0] if rounds else 0
