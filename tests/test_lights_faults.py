"""Every injected fault: the driver recovers where protocol v1 allows, else raises RigError; and in
every case the last thing the controller did is an OFF or its watchdog firing.

Commands are counted from 1 since the simulated controller was created; opening takes four
(ID, WATCHDOG, LEVEL, OFF), so the first command a test sends is number 5.
"""

from __future__ import annotations

import itertools
import socket
import threading
import time

import pytest
import serial
from helpers.device_servers import switch_through_served_device
from helpers.lights_doubles import CLOSE, expected_protocol, handshake
from typer.testing import CliRunner

from ps_lab.capture.light_controllers import LightState, SerialLightController
from ps_lab.capture.simulated.firmware import (
    Fault,
    LineAssembler,
    ManualClock,
    SimulatedFirmware,
    firmware_for,
    firmware_from_url,
    parse_faults,
    register_firmware,
)
from ps_lab.capture.simulated.pty_server import PtyServer
from ps_lab.cli import app
from ps_lab.errors import RigError

FIRST = 5  # number of the first command after the handshake
FAST = dict(reply_timeout=0.08, boot_timeout=0.08, retries=3)
# Over a pty the reply comes from another thread or process: allow for a busy machine where no
# timeout is meant to expire (a spurious expiry would only cost a retry).
PTY = dict(reply_timeout=0.5, boot_timeout=0.5, retries=3)
_names = itertools.count()


def open_sim(faults, *, lights=8, delay_s=0.3, seed=0, **options):
    """A controller on a fresh in-process simulator with a manual watchdog clock."""
    name = f"faults-{next(_names)}"
    firmware = SimulatedFirmware(
        lights, faults=faults, seed=seed, delay_s=delay_s, clock=ManualClock()
    )
    register_firmware(name, firmware)
    return SerialLightController(f"pslabsim://{name}", lights, **{**FAST, **options}), firmware


def fault_log(firmware):
    return [entry.text.split(" at ")[0] for entry in firmware.log if entry.kind == "fault"]


@pytest.mark.parametrize("kind", ["drop", "garble", "delay"])
def test_lost_garbled_or_late_reply_is_retried(kind):
    controller, firmware = open_sim([{"kind": kind, "at": FIRST}])
    with controller:
        controller.switch(3)
        assert firmware.state().lit == {3}
        controller.switch(4)  # a late reply still in flight must not confuse the next exchange
        assert controller.state().lit == {4}
    assert fault_log(firmware) == [f"{kind}@{FIRST}"]
    assert firmware.commands()[4:6] == ["ON 3", "ON 3"]
    assert firmware.ended_safely()


def test_reboot_during_a_command_rehandshakes_and_resends():
    controller, firmware = open_sim([Fault("reboot", at=FIRST)])
    with controller:
        controller.switch(3)
        assert firmware.state().lit == {3}
        assert firmware.boots == 2  # opening the port, then the fault
    assert firmware.commands()[4:7] == ["WATCHDOG 10000", "LEVEL 255", "ON 3"]
    assert firmware.ended_safely()


def test_reboot_while_lit_restores_the_lit_lights_and_level():
    controller, firmware = open_sim([Fault("reboot", at=FIRST + 2)], level=200)
    with controller:
        controller.switch(6)  # FIRST
        controller.set_level(90)  # FIRST + 1
        assert controller.state() == LightState(frozenset({6}), 90)  # FIRST + 2 reboots
        assert firmware.state() == LightState(frozenset({6}), 90)
    assert firmware.commands()[6:10] == ["WATCHDOG 10000", "LEVEL 90", "ON 6", "STATE"]
    assert firmware.ended_safely()


def test_controller_that_stops_answering_raises_and_its_watchdog_switches_off():
    controller, firmware = open_sim("silence@6", watchdog_ms=2000)
    with pytest.raises(
        RigError, match=r"no valid reply to 'ON 4' after 4 attempts \(received: nothing"
    ):
        with controller:
            controller.switch(3)
            controller.switch(4)
    assert controller.closed
    assert firmware.state().lit == {3}  # hung with light 3 on ...
    firmware.clock.advance(2.0)
    assert firmware.state().lit == frozenset()  # ... until the watchdog set by the driver fires
    assert firmware.log[-1].kind == "watchdog"
    assert firmware.ended_safely()


@pytest.mark.parametrize("kind", ["drop", "garble", "delay"])
def test_persistent_fault_raises_after_bounded_retries_then_switches_off(kind):
    faults = [{"kind": kind, "at": FIRST + i} for i in range(4)]  # every attempt of one command
    controller, firmware = open_sim(faults, delay_s=1.0)  # later than all four attempts together
    with pytest.raises(RigError) as info:
        controller.switch(5)
    message = str(info.value)
    assert "'ON 5'" in message and "after 4 attempts" in message
    assert (
        "nothing" in message if kind in ("drop", "delay") else "'" in message.split("received:")[1]
    )
    # The emergency OFF right after the failure is the last command the controller executed.
    assert firmware.commands()[-1] == "OFF"
    assert firmware.ended_safely()
    controller.close()


def test_controller_that_keeps_rebooting_raises():
    controller, firmware = open_sim([Fault("reboot", at=FIRST + i) for i in range(4)])
    with pytest.raises(RigError, match="keeps rebooting"):
        controller.switch(2)
    controller.close()
    assert firmware.ended_safely()


def test_probabilistic_faults_are_survived_and_reproducible():
    runs = []
    for _ in range(2):
        controller, firmware = open_sim("drop@p0.1,garble@p0.1,reboot@p0.05", seed=11)
        with controller:
            for light in [1, 5, 2, 8, 3, 7, 4, 6] * 3:
                controller.switch(light)
                assert firmware.state().lit == {light}
        assert firmware.ended_safely()
        runs.append((fault_log(firmware), firmware.commands()))
    assert runs[0] == runs[1]
    assert len(runs[0][0]) >= 3  # the run did meet faults


def test_faults_over_the_pty():
    firmware = SimulatedFirmware(
        8, faults=[{"kind": "garble", "at": 1}, {"kind": "reboot", "at": 6}]
    )
    with PtyServer(firmware) as server:
        with SerialLightController(server.path, 8, **PTY) as controller:
            controller.switch(1)
            controller.switch(2)
            assert controller.state().lit == {2}
        assert firmware.ended_safely()
    assert fault_log(firmware) == ["garble@1", "reboot@6"]


def test_watchdog_fires_on_the_pty_server_clock():
    clock = ManualClock()
    firmware = SimulatedFirmware(4, clock=clock)
    with PtyServer(firmware) as server:
        controller = SerialLightController(server.path, 4, watchdog_ms=500, **PTY)
        controller.switch(2)
        clock.advance(0.5)
        assert firmware.state().lit == frozenset()
        assert firmware.log[-1].kind == "watchdog"
        controller.close()


# -- exact retry behaviour, on the byte level ---------------------------------------------------


def test_lost_reply_is_resent_byte_for_byte():
    script = handshake(8) + [(b"ON 3\n", b""), (b"ON 3\n", b"OK ON 3\n")] + CLOSE
    with expected_protocol(script) as port:
        with SerialLightController(port, 8, **FAST) as controller:
            controller.switch(3)


def test_stale_reply_is_rejected_and_the_command_resent():
    script = (
        handshake(8)
        + [
            (b"ON 3\n", b""),
            (b"ON 3\n", b"OK ON 3\n"),
            (b"ON 4\n", b"OK ON 3\n"),  # the late reply to the first ON 3 arrives now
            (b"ON 4\n", b"OK ON 4\n"),
        ]
        + CLOSE
    )
    with expected_protocol(script) as port:
        with SerialLightController(port, 8, **FAST) as controller:
            controller.switch(3)
            controller.switch(4)


def test_boot_announcement_answers_the_handshake():
    script = [(b"ID\n", b"")] + handshake(8)[1:] + CLOSE
    with expected_protocol(script, greeting=b"\x00\xffnoise\nREADY ps-lab-lights 1 8\n") as port:
        SerialLightController(port, 8, **FAST).close()


def test_error_reply_is_retried_then_raised_and_switches_off():
    refused = (b"ON 3\n", b"ERR 3 light out of range\n")
    script = handshake(8) + [refused] * 4 + [(b"OFF\n", b"OK OFF\n")] + CLOSE
    with expected_protocol(script) as port:
        controller = SerialLightController(port, 8, **FAST)
        with pytest.raises(RigError, match="refused 'ON 3' 4 times: ERR 3 light out of range"):
            controller.switch(3)
        controller.close()


def test_spurious_error_from_a_corrupted_command_is_retried():
    # "OFF" with one flipped bit arrives as "OGF": the controller answers ERR 1.
    script = (
        handshake(8) + [(b"OFF\n", b"ERR 1 unknown command\n"), (b"OFF\n", b"OK OFF\n")] + CLOSE
    )
    with expected_protocol(script) as port:
        with SerialLightController(port, 8, **FAST) as controller:
            controller.all_off()


@pytest.mark.parametrize(
    ("identity", "message"),
    [
        (b"ID ps-lab-lights 2 8\n", "protocol version 2"),
        (b"ID other-lights 1 8\n", "not a ps-lab light controller"),
        (b"hello\n", "no ps-lab light controller answers"),
    ],
)
def test_wrong_controller_is_refused(identity, message):
    # A wrong identity is believed when said twice; silence or noise after every retry.
    attempts = 2 if identity.startswith(b"ID") else 1 + 1 + FAST["retries"]
    with expected_protocol([(b"ID\n", identity)] * attempts) as port:
        with pytest.raises(RigError, match=message):
            SerialLightController(port, 8, **FAST)
    assert not port.is_open


def test_double_fails_when_an_exchange_is_not_consumed():
    with pytest.raises(pytest.fail.Exception, match="not consumed"):
        with expected_protocol(handshake(8) + [(b"ON 1\n", b"OK ON 1\n")]) as port:
            SerialLightController(port, 8, **FAST)


def test_double_fails_on_unexpected_bytes():
    with pytest.raises(pytest.fail.Exception, match="expected b'LEVEL 255"):
        with expected_protocol(handshake(8)) as port:
            with pytest.raises(RigError):
                SerialLightController(port, 8, level=7, **FAST)


# -- ports and fault specifications -------------------------------------------------------------


def test_missing_port_is_a_rig_error():
    with pytest.raises(
        RigError, match="cannot open light controller port /dev/ps-lab-no-such-port"
    ):
        SerialLightController("/dev/ps-lab-no-such-port", 8, **FAST)


def test_busy_port_is_a_rig_error():
    with PtyServer(lights=8) as server:
        with SerialLightController(server.path, 8, **PTY):
            with pytest.raises(RigError, match="cannot open"):
                SerialLightController(server.path, 8, **PTY)


def test_fault_specifications_in_every_form():
    expected = (Fault("garble", at=7), Fault("drop", probability=0.25))
    assert parse_faults("garble@7, drop@p0.25") == expected
    assert (
        parse_faults([{"kind": "garble", "at": 7}, {"kind": "drop", "probability": 0.25}])
        == expected
    )
    assert parse_faults([Fault("garble", at=7), "drop@p0.25"]) == expected
    assert parse_faults(None) == parse_faults("") == ()
    for bad, message in [
        ("melt@3", "unknown fault kind"),
        ("garble", "KIND@N"),
        ([{"kind": "drop", "when": 3}], "unknown key 'when'"),
        ([{"kind": "drop", "at": 0}], "command number >= 1"),
        ([{"kind": "drop"}], "needs 'at'"),
        ("drop@p1.5", "needs 'at'"),
    ]:
        with pytest.raises(RigError, match=message):
            parse_faults(bad)


def test_url_options_reach_the_firmware():
    name, firmware = firmware_from_url(
        "pslabsim://?lights=6&faults=drop@5&seed=3&delay=0.5&clock=manual"
    )
    assert (
        firmware.lights == 6
        and firmware.faults == (Fault("drop", at=5),)
        and firmware.delay_s == 0.5
    )
    assert isinstance(firmware.clock, ManualClock)
    assert firmware_for(name) is firmware
    with pytest.raises(RigError, match="unknown option 'colour'"):
        firmware_from_url("pslabsim://?colour=red")
    port = serial.serial_for_url(f"pslabsim://{name}", timeout=0.05)
    assert port.readline() == b"READY ps-lab-lights 1 6\n"  # opening the port resets the board
    with pytest.raises(serial.SerialException, match="has 6 lights"):
        serial.serial_for_url(f"pslabsim://{name}?lights=8")
    port.close()


# -- command line -------------------------------------------------------------------------------


def test_serve_sim_serves_a_pty_until_sigterm(tmp_path):
    # command 5 (the switch) gets a garbled reply, retried
    read_state = switch_through_served_device(
        ["serve-sim", "--lights", "4", "--fault", "garble@5"], tmp_path / "lights.json", 4, PTY,
        wait_s=30,
    )
    with pytest.raises(RigError, match="serve-sim"):
        read_state()


def test_rig_check_walks_every_light_and_reports_errors_in_one_line():
    name = f"check-{next(_names)}"
    firmware = SimulatedFirmware(5, clock=ManualClock())
    register_firmware(name, firmware)
    result = CliRunner().invoke(
        app, ["rig", "check", "--port", f"pslabsim://{name}", "--lights", "5"]
    )
    assert result.exit_code == 0, result.output
    assert "5 lights switched one by one" in result.output
    assert [c for c in firmware.commands() if c.startswith("ON")] == [
        f"ON {i}" for i in range(1, 6)
    ]
    assert firmware.ended_safely()

    result = CliRunner().invoke(
        app, ["rig", "check", "--port", f"pslabsim://{name}", "--lights", "6"]
    )
    assert result.exit_code == 2
    assert "has 5 lights, expected 6" in result.output


def test_socket_url_reaches_a_controller_over_tcp():
    # A controller behind a TCP serial bridge (ser2net and the like): pyserial's socket:// URL.


    firmware = SimulatedFirmware(8, faults="drop@5", clock=ManualClock())
    listener = socket.create_server(("127.0.0.1", 0))
    host, port = listener.getsockname()

    def bridge():
        connection, _ = listener.accept()
        assembler = LineAssembler()
        with connection:
            while data := connection.recv(4096):
                for line in assembler.feed(data):
                    for reply in firmware.handle_line(line):
                        connection.sendall(reply.encode("latin-1") + b"\n")

    thread = threading.Thread(target=bridge, daemon=True)
    thread.start()
    try:
        with SerialLightController(f"socket://{host}:{port}", 8, **PTY) as controller:
            controller.switch(7)  # command 5: reply dropped, retried
            assert controller.state().lit == {7}
    finally:
        listener.close()
        thread.join(timeout=5)
    assert firmware.commands()[4:6] == ["ON 7", "ON 7"]
    assert firmware.ended_safely()


@pytest.mark.parametrize("transport", ["url", "pty"])
def test_reboot_between_commands_is_noticed_and_recovered(transport):
    # A brown-out during an exposure: the board resets with no command in flight. The READY it
    # sends waits in the input; the next exchange must notice it, restore level and lights, and
    # count the reboot so that a capture session can tell the exposure may have run dark.
    firmware = SimulatedFirmware(8, clock=ManualClock())
    if transport == "url":
        name = f"brownout-{next(_names)}"
        register_firmware(name, firmware)
        controller, server = SerialLightController(f"pslabsim://{name}", 8, **PTY), None
    else:
        server = PtyServer(firmware).start()
        controller = SerialLightController(server.path, 8, level=90, **PTY)
    try:
        controller.set_level(90)
        controller.switch(3)
        firmware.power_cycle()
        assert firmware.state() == LightState(frozenset(), 255)
        deadline = time.monotonic() + 5
        # Over the pty the READY crosses a thread: until it arrives, STATE honestly says NONE.
        while controller.state().lit != {3} and time.monotonic() < deadline:
            pass
        assert controller.reboots_seen == 1
        assert controller.state().lit == {3}
        assert firmware.state() == LightState(frozenset({3}), 90)
        controller.close()
        assert firmware.ended_safely()
    finally:
        if server is not None:
            server.stop()


def test_reboot_between_commands_on_the_byte_level():
    script = (
        handshake(8)
        + [
            (b"ON 3\n", b"OK ON 3\nREADY ps-lab-lights 1 8\n"),  # the board resets after replying
            (b"WATCHDOG 10000\n", b"OK WATCHDOG 10000\n"),
            (b"LEVEL 255\n", b"OK LEVEL 255\n"),
            (b"ON 3\n", b"OK ON 3\n"),  # what was lit is lit again before STATE is asked
            (b"STATE\n", b"STATE 3\n"),
        ]
        + CLOSE
    )
    with expected_protocol(script) as port:
        with SerialLightController(port, 8, **FAST) as controller:
            controller.switch(3)
            assert controller.reboots_seen == 0
            assert controller.state().lit == {3}
            assert controller.reboots_seen == 1
