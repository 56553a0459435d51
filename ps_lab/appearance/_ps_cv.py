"""The ``ps`` model's cross-validated score for ``--appearance auto``
(:func:`ps_lab.appearance.choice.resolve_model`'s ``ps_scorer``).

``ps`` is not a linear smoother: it is refitted ``PS_FOLDS`` times on the pixel sample, each time
without the lights of index ``i % PS_FOLDS == fold``, and predicts those (the normals stay those
solved on all the given lights); scored as the smoothers are.
"""

from __future__ import annotations

import numpy as np

from ps_lab.appearance.blocks import fit_block
from ps_lab.appearance.choice import grey_srgb, psnr_per_light
from ps_lab.appearance.models import PS_TERMS, Appearance, evaluate_appearance

__all__ = ["PS_FOLDS", "ps_cv_score"]

#: Folds of the ps model's cross-validation over the lights.
PS_FOLDS = 8


def ps_cv_score(
    sample: np.ndarray, lights: np.ndarray, normals: np.ndarray, albedo: np.ndarray
) -> float:
    """The ``ps`` model's cross-validated score on a pixel sample (module docstring).

    Parameters
    ----------
    sample : ndarray of shape (n, m, C)
    lights : ndarray of shape (n, 3)
    normals : ndarray of shape (m, 3)
    albedo : ndarray of shape (m,) or (m, C)

    Returns
    -------
    float
        Mean over the lights of the grey sRGB PSNR (dB) of their held-out predictions.

    """
    obs = np.ascontiguousarray(sample, np.float64)
    n, m, c = obs.shape
    lights = np.asarray(lights, np.float64)
    normals = np.nan_to_num(np.asarray(normals, np.float64))
    albedo = np.asarray(albedo, np.float64)
    albedo = albedo[:, None] if albedo.ndim == 1 else albedo
    predicted = np.zeros_like(obs)
    index = np.arange(n)
    meta = {"basis": "ps", "K": len(PS_TERMS), "terms": list(PS_TERMS), "channels": c,
            "visibility": "clip-linear"}
    for fold in range(PS_FOLDS):
        held, kept = index[index % PS_FOLDS == fold], index[index % PS_FOLDS != fold]
        coeffs, vis = fit_block("ps", np.ascontiguousarray(obs[kept]), lights[kept],
                                normals=normals, albedo=albedo)
        app = Appearance("ps", coeffs[None], meta,
                         {"visibility": vis[None]})
        for i in held:
            predicted[i] = evaluate_appearance(app, lights[i], normals[None],
                                               albedo[None])[0]
    truth = grey_srgb(np.clip(obs, 0.0, 1.0))
    return float(np.mean(psnr_per_light(grey_srgb(np.clip(predicted, 0.0, 1.0)), truth)))
