"""Injected faults of the simulated devices: one :class:`Fault` type.

Also the parser of the ``KIND@N`` / ``KIND@pP`` specifications that URLs and
``ps-lab rig serve-sim --fault`` give.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from ps_lab.errors import RigError

#: What can go wrong, in the controller's words:
#: drop - the command is executed but its reply is lost;
#: garble - the command is executed but one or two bits of its reply are flipped;
#: delay - the command is executed and its reply arrives ``delay_s`` later (past the timeout);
#: reboot - the controller resets instead of executing: sends READY, forgets lights/level/watchdog;
#: silence - the controller hangs: it ignores this and every later command and never answers
#: again; its watchdog still switches the lights off (on the Arduino the AVR hardware watchdog
#: resets a hung sketch, and a reset switches every output off).
FAULT_KINDS = ("drop", "garble", "delay", "reboot", "silence")
#: The simulated camera's: a capture that never returns a file, a file cut short.
CAMERA_FAULT_KINDS = ("timeout", "truncated")
#: The PTP/IP camera simulator's (at the n-th InitiateCapture): answered DeviceBusy; accepted but
#: never reported (no ObjectAdded); both connections dropped halfway through the download; the
#: download spread over seconds.
PTPIP_FAULT_KINDS = ("busy", "timeout", "disconnect", "slow")


@dataclass(frozen=True)
class Fault:
    """One injected fault.

    Attributes
    ----------
    kind : str
        One of :data:`FAULT_KINDS` (the controller's) or :data:`CAMERA_FAULT_KINDS`.
    at : int or None
        Fire at this 1-based count in the device's own units: protocol commands for the
        controller (the N-th command line it receives), capture calls for the camera (re-shoots
        included).
    probability : float
        Otherwise (controller only), fire at each command with this probability (seeded
        generator).

    """

    kind: str
    at: int | None = None
    probability: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in (*FAULT_KINDS, *CAMERA_FAULT_KINDS, *PTPIP_FAULT_KINDS):
            raise RigError(
                f"unknown fault kind {self.kind!r}; choose from {', '.join(FAULT_KINDS)}"
            )
        if self.at is None and not 0.0 < self.probability <= 1.0:
            raise RigError(
                f"fault {self.kind!r} needs 'at' (command number) or 'probability' in (0, 1]"
            )
        if self.at is not None and (
            isinstance(self.at, bool) or not isinstance(self.at, int) or self.at < 1
        ):
            raise RigError(
                f"fault {self.kind!r}: 'at' must be a command number >= 1, got {self.at!r}"
            )

    def __str__(self) -> str:
        return (
            f"{self.kind}@{self.at}"
            if self.at is not None
            else f"{self.kind}@p{self.probability:g}"
        )


_FAULT_TEXT = re.compile(r"^\s*([a-z]+)\s*@\s*(p?)([0-9.eE+-]+)\s*$")


def _parse(spec: Any) -> tuple[Fault, ...]:
    """:func:`parse_faults` without the check that every kind is the controller's."""
    if spec is None or spec == "":
        return ()
    if isinstance(spec, Fault):
        return (spec,)
    if isinstance(spec, str):
        faults = []
        for item in filter(None, (part.strip() for part in spec.split(","))):
            match = _FAULT_TEXT.match(item)
            if match is None:
                raise RigError(
                    f"cannot read fault {item!r}: write KIND@N or KIND@pP "
                    "(e.g. garble@7, drop@p0.1)"
                )
            kind, is_probability, number = match.groups()
            try:
                if is_probability:
                    faults.append(Fault(kind, probability=float(number)))
                else:
                    faults.append(Fault(kind, at=int(number)))
            except ValueError:
                raise RigError(f"cannot read fault {item!r}: {number!r} is not a number") from None
        return tuple(faults)
    if isinstance(spec, Mapping):
        unknown = set(spec) - {"kind", "at", "probability"}
        if unknown:
            raise RigError(
                f"unknown key {sorted(unknown)[0]!r} in fault {dict(spec)!r} "
                "(kind, at, probability)"
            )
        if "kind" not in spec:
            raise RigError(f"fault {dict(spec)!r} has no 'kind'")
        probability = spec.get("probability", 0.0)
        if isinstance(probability, bool) or not isinstance(probability, int | float):
            raise RigError(f"fault {dict(spec)!r}: 'probability' must be a number")
        return (Fault(str(spec["kind"]), at=spec.get("at"), probability=float(probability)),)
    if isinstance(spec, Iterable):
        return tuple(itertools.chain.from_iterable(_parse(item) for item in spec))
    raise RigError(f"cannot read fault specification {spec!r}")


def parse_faults(spec: Any) -> tuple[Fault, ...]:
    """Read a controller fault specification in any of the forms a URL or the CLI gives.

    Parameters
    ----------
    spec : None, str, Fault, mapping, or iterable of those
        ``"garble@7,drop@p0.05"`` (a fault at command 7, a fault with probability 0.05 per
        command), ``{"kind": "garble", "at": 7}``, ``{"kind": "drop", "probability": 0.05}``,
        or a list mixing these.

    Returns
    -------
    tuple of Fault

    """
    faults = _parse(spec)
    for fault in faults:
        if fault.kind not in FAULT_KINDS:
            raise RigError(
                f"unknown fault kind {fault.kind!r}; choose from {', '.join(FAULT_KINDS)}"
            )
    return faults


def parse_camera_faults(spec: Any) -> tuple[Fault, ...]:
    """Read PTP/IP camera faults (``"busy@2,disconnect@5"``): kinds of :data:`PTPIP_FAULT_KINDS`.

    ``at`` is the n-th InitiateCapture the camera receives; probabilities are not offered.
    """
    faults = _parse(spec)
    for fault in faults:
        if fault.kind not in PTPIP_FAULT_KINDS or fault.at is None:
            raise RigError(
                f"camera fault {fault}: write KIND@N with KIND one of "
                f"{', '.join(PTPIP_FAULT_KINDS)}"
            )
    return faults
