"""A reconstruction's verdict stamped in its volume's NIfTI header, for the steps after it.

``svr reconstruct`` and ``svr bids`` write the verdict (:class:`svr.reconstruction.result.Verdict`:
its status and the trust in its frame) into the ``descrip`` field of the volume they write, e.g.
``"fetal-svr verdict: ok; frame: trusted"``, so that a later step on that file alone
(``svr segment-volume``) knows whether the volume is in an atlas frame and whether it may be
measured. The field holds 80 bytes: the reasons stay in the log and the QA page. A volume from
another tool has no stamp, and is judged by what can be seen in it.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["STAMP_PREFIX", "VerdictStamp", "read_stamp", "verdict_stamp"]

STAMP_PREFIX = "fetal-svr verdict: "
"""How a stamp starts."""


class VerdictStamp(NamedTuple):
    """A stamp read back.

    Attributes:
        status: ``"ok"``, ``"warning"`` or ``"failed"``.
        frame: ``"scanner"``, ``"trusted"``, ``"uncertain"`` or ``"untrusted"``.
    """

    status: str
    frame: str

    def ok(self) -> bool:
        """Whether the volume is usable and in a trusted canonical frame."""
        return self.status == "ok" and self.frame == "trusted"

    def line(self) -> str:
        """The stamp in words, e.g. ``"warning, canonical frame uncertain"``."""
        frame = "scanner frame" if self.frame == "scanner" else f"canonical frame {self.frame}"
        return f"{self.status}, {frame}"


def verdict_stamp(status: str, frame: str) -> str:
    """The ``descrip`` text of a verdict (at most 80 bytes).

    Raises:
        ValueError: If ``status`` or ``frame`` is not one of the verdict's values.
    """
    if status not in ("ok", "warning", "failed"):
        raise ValueError(f"verdict_stamp(): 'status' must be ok, warning or failed, got {status!r}")
    if frame not in ("scanner", "trusted", "uncertain", "untrusted"):
        raise ValueError(
            "verdict_stamp(): 'frame' must be scanner, trusted, uncertain or untrusted, "
            f"got {frame!r}"
        )
    return f"{STAMP_PREFIX}{status}; frame: {frame}"


def read_stamp(descrip: str | bytes) -> VerdictStamp | None:
    """The verdict stamped in a ``descrip`` field, or ``None`` where there is none."""
    text = descrip.decode("latin-1") if isinstance(descrip, bytes) else descrip
    text = text.rstrip("\x00").strip()
    if not text.startswith(STAMP_PREFIX):
        return None
    status, _, frame = text[len(STAMP_PREFIX) :].partition("; frame: ")
    if status not in ("ok", "warning", "failed") or not frame:
        return None
    return VerdictStamp(status, frame)
