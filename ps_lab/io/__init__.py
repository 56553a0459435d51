"""Files and folder contracts: the bottom layer of ps_lab, importing nothing above it.

- :mod:`~ps_lab.io.files`: the one atomic write, staged output folder, sha256 and JSON-safe helper
- :mod:`~ps_lab.io.images`: image readers and writers (PNG, TIFF, PFM, .npy, RAW)
- :mod:`~ps_lab.io.raw`: linear RAW loading (rawpy), black/white levels, saturation mask
- :mod:`~ps_lab.io.dng`: a minimal linear DNG writer (the simulated camera's files)
- :mod:`~ps_lab.io.light_files`: light-direction and light-intensity tables (DiLiGenT text files)
- :mod:`~ps_lab.io.run`: the run format (``manifest.json``, ``"ps-lab-run"``): names, read, write
- :mod:`~ps_lab.io.result`: the result format (``metrics.json``, ``"ps-lab-reconstruction"``)
- :mod:`~ps_lab.io.frames`: which files are the frames of an image folder or a capture run
- :mod:`~ps_lab.io.dataset`: load or open an image folder or a capture run
- :mod:`~ps_lab.io.truth`: ground-truth normals, whole or band by band
- :mod:`~ps_lab.io.bands`: row bands and the observation store
"""
