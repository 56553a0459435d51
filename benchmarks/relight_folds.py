"""ps-lab's default appearance against RelightLab's fits, eight folds of held-out lights (issue 38).

    python benchmarks/relight_folds.py ../shared/data/realrti-3 --cache /tmp/relight-folds

For every capture (a folder with images and an ``.lp`` file) and fold ``f`` (the lights with index
``i % 8 == f`` held out): RelightLab's ``relight-cli`` (``../shared/tools/relightlab/run``) fits PTM,
HSH (27 planes), RBF and BLN (18 planes) on a folder whose ``.lp`` lists the training images only,
in linear (its default) and in sRGB (``-I srgb``), and renders every held-out light
(``-L x:y:z -D``); the renders are cached under ``--cache`` (one run per capture, fold, model and
space; rerunning skips what is there). ps-lab's side is ``ps-lab bench relight`` 's
:func:`ps_lab.bench.relight.evaluate_capture` (``auto``, the default, and ``ps``). Metric: grey
(channel mean of linear RGB), sRGB-encoded, PSNR per image at peak 255, mean over the held-out
images, then over the folds. RelightLab writes its linear fits' renders as linear values and its
sRGB fits' as sRGB (checked against the figures in ``realrti-3/README.md``). Prints a markdown table:
per capture the fold mean of each contender, and the default's margin over the best contender
(fold mean, and the smallest per-fold margin).
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import cv2
import numpy as np

from ps_lab.bench.relight import evaluate_capture, find_captures
from ps_lab.io.encoding import linear_to_srgb, srgb_to_linear
from ps_lab.io.light_files import find_lp

TOOL = Path(__file__).resolve().parents[1].parent / "shared" / "tools" / "relightlab" / "run"
CONTENDERS = [(m, s) for m in ("ptm", "hsh", "rbf", "bln") for s in ("linear", "srgb")]
FOLDS = 8


def _lp_rows(capture: Path) -> list[list[str]]:
    lines = find_lp(capture).read_text().splitlines()[1:]
    return [line.split() for line in lines if len(line.split()) >= 4]


def _grey(linear: np.ndarray) -> np.ndarray:
    return linear_to_srgb(linear.mean(axis=-1)) * 255.0


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0**2 / max(float(np.mean((a - b) ** 2)), 1e-12)))


def relightlab_fold(capture: Path, fold: int, model: str, space: str, cache: Path) -> float:
    """RelightLab's held-out grey PSNR (dB) of one fold, running it when not cached."""
    rows = _lp_rows(capture)
    held = [r for i, r in enumerate(rows) if i % FOLDS == fold]
    out = cache / capture.name / f"f{fold}" / f"{model}_{space}"
    if not (out / "done").exists():
        train = cache / capture.name / f"f{fold}" / "capture"
        train.mkdir(parents=True, exist_ok=True)
        kept = [r for i, r in enumerate(rows) if i % FOLDS != fold]
        for r in kept:
            link = train / r[0]
            if not link.exists():
                link.symlink_to((capture / r[0]).resolve())
        (train / "dirs.lp").write_text(f"{len(kept)}\n" + "".join(" ".join(r[:4]) + "\n"
                                                                  for r in kept))
        out.mkdir(parents=True, exist_ok=True)
        planes = "27" if model == "hsh" else "18"
        colour = ["-I", "srgb"] if space == "srgb" else []
        fit = out / "fit"
        subprocess.run([str(TOOL), "relight-cli", "-b", model, "-p", planes, *colour, str(train),
                        str(fit)], check=True, capture_output=True)
        for r in held:
            subprocess.run([str(TOOL), "relight-cli", "-L", ":".join(r[1:4]), "-D",
                            str(out / (Path(r[0]).stem + ".png")), str(fit)], check=True,
                           capture_output=True)
        subprocess.run(["rm", "-rf", str(fit)], check=True)
        (out / "done").touch()
    scores = []
    for r in held:
        truth = _grey(srgb_to_linear(cv2.imread(str(capture / r[0]))[..., ::-1] / 255.0))
        render = cv2.imread(str(out / (Path(r[0]).stem + ".png")), cv2.IMREAD_UNCHANGED)
        values = render[..., :3][..., ::-1] / 255.0
        linear = values if space == "linear" else srgb_to_linear(values)
        scores.append(_psnr(_grey(linear), truth))
    return float(np.mean(scores))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/relight-folds"))
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    results = {}
    for capture in find_captures(args.folder):
        row = evaluate_capture(capture, models=("auto", "ps"))
        theirs = {f"{m} {s}": [relightlab_fold(capture, f, m, s, args.cache)
                               for f in range(FOLDS)] for m, s in CONTENDERS}
        results[capture.name] = {"auto": row.cells["auto"]["folds"],
                                 "ps": row.cells["ps"]["folds"], "choices": row.choices, **theirs}
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))
    names = ["auto", "ps"] + [f"{m} {s}" for m, s in CONTENDERS]
    print("| capture | " + " | ".join(names) + " | margin mean / min fold |")
    print("|---" * (len(names) + 2) + "|")
    for capture, cells in results.items():
        theirs = np.array([cells[f"{m} {s}"] for m, s in CONTENDERS])
        mine = np.array(cells["auto"])
        margin = mine.mean() - theirs.mean(axis=1).max()
        worst = float(np.min(mine - theirs.max(axis=0)))
        print(f"| {capture} | " + " | ".join(f"{np.mean(cells[n]):.2f}" for n in names)
              + f" | {margin:+.2f} / {worst:+.2f} |")


if __name__ == "__main__":
    main()
