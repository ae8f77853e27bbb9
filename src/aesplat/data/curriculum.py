"""View-gap curriculum: the allowed context-frame gap grows with the global step (docs/data.md)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GapCurriculum:
    """Allowed context gap [lo, hi] (frames), interpolated linearly from ``initial`` to ``final`` over
    ``warmup_steps`` global steps and constant afterwards. Paper setting: 25 -> 90 frames."""

    initial: tuple[int, int] = (25, 25)
    final: tuple[int, int] = (25, 90)
    warmup_steps: int = 150_000

    def __post_init__(self) -> None:
        for name, (lo, hi) in (("initial", self.initial), ("final", self.final)):
            if not 1 <= lo <= hi:
                raise ValueError(f"curriculum {name} gap range must satisfy 1 <= lo <= hi, got ({lo}, {hi})")
        if self.warmup_steps < 0:
            raise ValueError(f"warmup_steps must be >= 0, got {self.warmup_steps}")

    def allowed(self, step: int) -> tuple[int, int]:
        """The inclusive gap range allowed at global ``step``."""
        t = 1.0 if self.warmup_steps == 0 else min(max(step / self.warmup_steps, 0.0), 1.0)
        lo = round(self.initial[0] + (self.final[0] - self.initial[0]) * t)
        hi = round(self.initial[1] + (self.final[1] - self.initial[1]) * t)
        return lo, max(lo, hi)

    def span(self) -> tuple[int, int]:
        """Every gap the curriculum allows at some step: [smallest lo, largest hi]."""
        return min(self.initial[0], self.final[0]), max(self.initial[1], self.final[1])

    def accepts(self, gap: int, step: int) -> bool:
        lo, hi = self.allowed(step)
        return lo <= gap <= hi
