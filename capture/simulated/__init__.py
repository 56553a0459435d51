"""Simulated devices a rig file can select (python-microscope's ``simulators/``).

- :mod:`~ps_lab.capture.simulated.firmware`: the light controller's firmware (protocol v1), faults
- :mod:`~ps_lab.capture.simulated.pty_server`: that firmware served on a pseudo-terminal
- :mod:`~ps_lab.capture.simulated.protocol_pslabsim`: the pyserial ``pslabsim://`` URL handler
- :mod:`~ps_lab.capture.simulated.simulated_camera`: :class:`SimulatedCamera`, rendering and
  writing DNG
- :mod:`~ps_lab.capture.simulated.avr_firmware`: the real sketch, compiled, running in simavr
- :mod:`~ps_lab.capture.simulated.simulation`: a rig's ``[scene]`` as the renderer's scene, its
  true lights, and the ground truth a run records (``simulation/``)
- :mod:`~ps_lab.capture.simulated.board_frames`: a simulated camera's ChArUco board frames

Production code imports this package only through :mod:`ps_lab.capture.connect` (checked by
import-linter), each module when a rig selects it; this package is the only part of capture
that imports :mod:`ps_lab.render`. Test doubles live under ``tests/helpers``.
"""
