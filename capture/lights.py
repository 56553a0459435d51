"""Light controllers: the abstract base and the serial driver for protocol v1 (docs/rig-protocol.md)."""

from __future__ import annotations

from dataclasses import dataclass

import serial

PROTOCOL_NAME = "ps-lab-lights"
PROTOCOL_VERSION = 1
DEFAULT_WATCHDOG_MS = 10000
MAX_LEVEL = 255
#: Longest command line (without its terminator) a controller must accept.
MAX_LINE = 200

# pyserial finds a ``scheme://`` handler by importing ``protocol_<scheme>`` from these packages;
# this makes ``pslabsim://`` (capture/protocol_pslabsim.py) available to every serial_for_url call.
if "ps_lab.capture" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("ps_lab.capture")


@dataclass(frozen=True)
class LightState:
    """What a light controller reports as lit.

    Attributes
    ----------
    lit : frozenset of int
        Lit lights, numbered 1..N.
    level : int
        PWM brightness of lit lights, 0-255.
    """

    lit: frozenset[int]
    level: int
