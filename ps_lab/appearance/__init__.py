"""Appearance and relighting: one layer above io, beside render, below the stages.

- :mod:`~ps_lab.appearance.models`: the per-pixel models (PTM, HSH, RBF/BLN/GP, ``ps``), their
  bases and their evaluation under a light
- :mod:`~ps_lab.appearance.smoothers`: the weights of the interpolating models (rbf, bln, gp)
- :mod:`~ps_lab.appearance.store`: the ``appearance.npz`` file of a result folder
- :mod:`~ps_lab.appearance.design`: which terms the captured lights determine
- :mod:`~ps_lab.appearance.fit`: the fit beside the normals (``ps-lab reconstruct
  --appearance``), band by band or on whole arrays; :mod:`~ps_lab.appearance.blocks` the
  per-block fits and their numba kernels (``_ps_kernel``, ``_ps_terms``)
- :mod:`~ps_lab.appearance.choice`: ``--appearance auto`` by cross-validation (``_ps_cv``)
- :mod:`~ps_lab.appearance.relight`: ``ps-lab relight``, a result relit under new lights
- :mod:`~ps_lab.appearance.relightlab`: RelightLab's / OpenLIME's web layout, read and write;
  :mod:`~ps_lab.appearance.rbf_conversion` any model converted to its ``rbf`` layout;
  :mod:`~ps_lab.appearance.export` a result exported to it (``ps-lab view --format relight``)

Nothing is imported here: reading and relighting a fit (the viewer, ``ps-lab relight``) loads no
numba kernel; only :mod:`~ps_lab.appearance.blocks` (a fit) does.
"""
