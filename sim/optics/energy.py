"""Where one LED's light went: the energy books and the per-LED trace record (no torch)."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Energy", "SourceTrace"]


@dataclass
class Energy:
    """Where one LED's unit power went (fractions of the emitted power)."""

    emitted: float = 0.0
    on_screen: float = 0.0
    elsewhere: float = 0.0
    reflected: float = 0.0
    absorbed: float = 0.0

    @property
    def residual(self) -> float:
        """``emitted - (on_screen + elsewhere + reflected + absorbed)``: zero to rounding."""
        return self.emitted - (self.on_screen + self.elsewhere + self.reflected + self.absorbed)

    def as_dict(self) -> dict:
        return {"emitted": self.emitted, "on_screen": self.on_screen, "elsewhere": self.elsewhere,
                "reflected": self.reflected, "absorbed": self.absorbed, "residual": self.residual}


@dataclass
class SourceTrace:
    """What tracing one LED produced besides the accumulated images.

    ``seconds`` is the wall time of the trace; ``compile_seconds`` the part of it spent
    compiling or loading compiled code (the kernel's first call in a process), else 0.
    """

    led: int
    rays: int
    seconds: float
    energy: Energy
    counters: dict = field(default_factory=dict)
    engine: str = "torch"
    compile_seconds: float = 0.0
