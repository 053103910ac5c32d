"""What can go wrong in an evaluation: a setup error (stops before scoring) or the failure
of one sample (collected, the others are still scored)."""

from __future__ import annotations

import dataclasses


class EvaluationSetupError(ValueError):
    """The evaluation cannot start: no samples, missing predictions or origins, bad options.

    ``dego eval`` prints it as one ``error: ...`` line and exits with status 2.
    """


class EvaluationWorkerError(RuntimeError):
    """A ``--workers`` process died (killed by a signal, or exited) before the totals were
    sent: no report is made. ``dego eval`` prints it as one ``error: ...`` line and exits
    with status 1."""


@dataclasses.dataclass(frozen=True)
class SampleFailure:
    """A sample that could not be scored: its token, the file at fault and why."""

    token: str
    file: str
    message: str

    def as_dict(self) -> dict[str, str]:
        return {"token": self.token, "file": self.file, "message": self.message}


def list_tokens(tokens: list[str] | tuple[str, ...], limit: int = 10) -> str:
    """``"a, b, c"`` for at most ``limit`` tokens, ``"... and N more"`` after that."""
    shown = ", ".join(repr(t) for t in tokens[:limit])
    return shown + (f" ... and {len(tokens) - limit} more" if len(tokens) > limit else "")


__all__ = ["EvaluationSetupError", "EvaluationWorkerError", "SampleFailure", "list_tokens"]
