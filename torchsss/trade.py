"""The speed/accuracy trade of a scene, measured: every applicable method over a sweep of its knobs.

:func:`trade` renders the scene with the reference (the truth: its default knobs) and then, for each method that
can render the scene, each configuration of :func:`sweep_configs`: build once (``setup_s``), ``frames`` frames with
the light orbiting the object (median ``frame_s``), the error of the first frame (the scene's own lighting)
against the reference (:func:`image_error`) and the peak resident memory the run added (:class:`PeakMemory`).
:func:`write_trade` writes ``trade.json`` (one row per run) and ``trade.png`` (error against frame time per
method, log axes, the Pareto front marked; a second panel against setup time). ``python -m torchsss trade SCENE
--out DIR`` is the command; :func:`pareto_front` and the rows feed the planner (:mod:`torchsss.plan`).

Lengths are millimetres, times seconds, memory MiB.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from tqdm import tqdm

from torchsss._json import jsonable
from torchsss.pipelines import RenderResult
from torchsss.registry import ENVIRONMENT_METHODS, OBJECT_METHODS, render_scene
from torchsss.scene import Scene

__all__ = ["ATLAS_METHODS", "PeakMemory", "applicable_methods", "image_error", "pareto_front", "plot_trade",
           "run_config", "sweep_configs", "trade", "write_trade"]

#: Methods that parametrise the surface with an xatlas atlas (their setup grows with the face count).
ATLAS_METHODS = frozenset({"lensch", "icdf", "hybrid"})
#: Face count above which the sweep also decimates the mesh for the atlas methods.
ATLAS_FACES = 20_000


def applicable_methods(scene: Scene) -> list[str]:
    """The translucency methods that can render ``scene`` (``reference`` first; caustics scenes: none).

    Examples:
        >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
        ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
        ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 8, "height": 8}})
        >>> applicable_methods(s)
        ['reference', 'splat', 'icdf', 'hybrid', 'lensch']
    """
    if scene.caustics is not None:
        return []
    methods = ["reference", "splat", "icdf", "hybrid", "lensch"]
    if len(scene.objects) > 1:
        methods = [m for m in methods if m in OBJECT_METHODS]
    if any(type(light).__name__ == "EnvironmentLight" for light in scene.lights):
        methods = [m for m in methods if m in ENVIRONMENT_METHODS]
    return methods


def sweep_configs(method: str, *, quick: bool = False, faces: int = 0) -> list[dict]:
    """The knob configurations the sweep renders for ``method``, from large error to below 1%.

    Each configuration is a dict of renderer knobs; the atlas methods get ``"source_faces"`` (their atlas and
    precompute on the mesh decimated to :data:`ATLAS_FACES` faces; the camera sees the full mesh) when the mesh has
    more faces than that. (``"decimate"``, the scene's decimation, is understood by :func:`run_config` too.)
    ``quick`` keeps a few points per method (about a minute on the default scene at 64 x 64).

    * reference: ``eps`` 0.3, 0.1, 0.03 (the sample spacing's tolerance; the truth uses 0.01).
    * splat: ``eps`` 0.1, 0.03, 0.01, 0.003 (the splat budget, Shah eq. 6.16-6.18) and ``oversample`` 1 and 2.
    * icdf: ``samples`` 1024 ... 65536 (error ~ 1/sqrt(N)).
    * hybrid: ``samples`` 1024 ... 65536.
    * lensch: ``atlas_resolution`` 128, 256, 512, 1024.

    Examples:
        >>> sweep_configs("icdf", quick=True)
        [{'samples': 1024}, {'samples': 8192}]
    """
    if quick:
        grids = {"reference": [{"eps": 0.1}],
                 "splat": [{"eps": 0.1}, {"eps": 0.01}],
                 "icdf": [{"samples": 1024}, {"samples": 8192}],
                 "hybrid": [{"samples": 4096}],
                 "lensch": [{"atlas_resolution": 128}]}
    else:
        grids = {"reference": [{"eps": e} for e in (0.3, 0.1, 0.03)],
                 "splat": [{"eps": e, "oversample": s} for e in (0.1, 0.03, 0.01, 0.003) for s in (1.0, 2.0)],
                 "icdf": [{"samples": n} for n in (1024, 4096, 16384, 65536)],
                 "hybrid": [{"samples": n} for n in (1024, 4096, 16384, 65536)],
                 "lensch": [{"atlas_resolution": r} for r in (128, 256, 512, 1024)]}
    if method not in grids:
        raise ValueError(f"method: expected one of {sorted(grids)}, got {method!r}")
    configs = [dict(c) for c in grids[method]]
    if method in ATLAS_METHODS and faces > ATLAS_FACES:
        configs = [{**c, "source_faces": ATLAS_FACES} for c in configs]
    return configs


def image_error(result: RenderResult, reference: RenderResult) -> dict[str, float]:
    """Relative RMSE and max error of ``result`` against ``reference`` over the pixels both cover.

    ``rel_rmse`` is :math:`\\sqrt{\\langle (L - L_{ref})^2 \\rangle} / \\sqrt{\\langle L_{ref}^2 \\rangle}` over the
    covered pixels and the three channels; ``max_error`` is :math:`\\max |L - L_{ref}| / \\max L_{ref}` (relative
    to the brightest reference value, so that it is bounded where the reference is dark).

    Raises:
        ValueError: images of different shapes, or no pixel covered by both.
    """
    if result.radiance.shape != reference.radiance.shape:
        raise ValueError(f"result: expected the reference's shape {tuple(reference.radiance.shape)}, got "
                         f"{tuple(result.radiance.shape)}")
    m = (result.mask & reference.mask).expand_as(reference.radiance)
    if not bool(m.any()):
        raise ValueError("result: expected some pixels covered by both images, got none")
    ref = reference.radiance[m].double()
    d = result.radiance[m].double() - ref
    scale = float(ref.square().mean().sqrt())
    peak = float(ref.abs().max())
    return {"rel_rmse": float(d.square().mean().sqrt()) / scale if scale > 0 else math.inf,
            "max_error": float(d.abs().max()) / peak if peak > 0 else math.inf}


class PeakMemory:
    """Peak resident memory (MiB) a block adds, sampled from ``/proc/self/statm`` every ``interval`` seconds.

    ``with PeakMemory() as pm: ...`` then ``pm.peak_mib`` is the largest resident set size seen during the block
    minus the size at its start (0 where ``/proc`` is unavailable: ``pm.available`` is False).
    """

    def __init__(self, interval: float = 0.01) -> None:
        self.interval = float(interval)
        self.available = os.path.exists("/proc/self/statm")
        self.peak_mib = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._start = 0.0
        self._max = 0.0

    @staticmethod
    def rss_mib() -> float:
        """The process's resident set size now, MiB (0 without ``/proc``)."""
        try:
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
        except (OSError, ValueError, IndexError):
            return 0.0

    def _watch(self) -> None:
        while not self._stop.wait(self.interval):
            self._max = max(self._max, self.rss_mib())

    def __enter__(self) -> PeakMemory:
        gc.collect()
        self._start = self._max = self.rss_mib()
        if self.available:
            self._thread = threading.Thread(target=self._watch, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._max = max(self._max, self.rss_mib())
        self.peak_mib = max(0.0, self._max - self._start)


def pareto_front(rows: Sequence[dict], cost: str = "frame_s", error: str = "rel_rmse") -> list[int]:
    """Indices of the rows no other row beats in both ``cost`` and ``error`` (lower is better), by cost.

    Examples:
        >>> pareto_front([{"frame_s": 1, "rel_rmse": 0.1}, {"frame_s": 2, "rel_rmse": 0.2},
        ...               {"frame_s": 3, "rel_rmse": 0.01}])
        [0, 2]
    """
    order = sorted(range(len(rows)), key=lambda i: (rows[i][cost], rows[i][error]))
    front, best = [], math.inf
    for i in order:
        if rows[i][error] < best:
            front.append(i)
            best = rows[i][error]
    return front


def _with_decimation(scene: Scene, knobs: dict) -> tuple[Scene, dict]:
    knobs = dict(knobs)
    target = knobs.pop("decimate", None)
    if target is not None:
        scene = dataclasses.replace(scene, decimate=int(target))
    return scene, knobs


def run_config(scene: Scene, method: str, knobs: dict, frames: int, dtype: torch.dtype) -> tuple[RenderResult, float]:
    """Build ``method`` with ``knobs`` (``"decimate"``: the scene's decimation), render ``frames`` frames.

    Returns the first frame's result (``stats["total_s"]`` added) and the peak resident memory added (MiB).
    """
    scene, knobs = _with_decimation(scene, knobs)
    with PeakMemory() as pm:
        t0 = time.perf_counter()
        result = render_scene(scene, method, dtype=dtype, frames=frames, **knobs)
        result.stats["total_s"] = time.perf_counter() - t0
    return result, pm.peak_mib


def trade(scene: Scene, *, methods: Sequence[str] | None = None, quick: bool = False, frames: int | None = None,
          dtype: torch.dtype = torch.float32, progress: bool = True,
          configs: Callable[[str], list[dict]] | None = None) -> dict:
    """Measure ``scene``'s trade: the reference, then each method over its knob sweep (:func:`sweep_configs`).

    Args:
        scene: a scene the reference renders (single object, or several for reference and splat).
        methods: the methods to sweep (default: :func:`applicable_methods` without the reference's truth run).
        quick: the small sweep (:func:`sweep_configs` ``quick``) and 2 frames per run.
        frames: frames per configuration (light orbit; default 3, quick 2).
        dtype: the renders' dtype.
        progress: a progress bar over the sweep.
        configs: ``method -> list of knob dicts`` instead of :func:`sweep_configs`.

    Returns:
        ``{"scene", "reference": {...}, "rows": [...], "pareto": [...], "seconds"}``; each row holds ``method``,
        ``knobs`` (as given), ``setup_s``, ``frame_s`` (median), ``total_s``, ``rel_rmse``, ``max_error``,
        ``peak_mib`` and ``stats_knobs`` (every knob as the renderer resolved it); a configuration that refuses
        to build (a ValueError, e.g. Lensch's throughput over its memory cap) gets a row with ``refused`` (the
        message) instead; ``pareto`` lists the indices of the rows on the error / frame-time front.

    Raises:
        ValueError: a caustics scene (nothing to trade), or an unknown or inapplicable method.
    """
    allowed = applicable_methods(scene)
    if not allowed:
        raise ValueError("scene: expected a translucent scene for trade, got a caustics scene (trade sweeps the "
                         "subsurface methods)")
    methods = list(allowed) if methods is None else list(methods)
    for m in methods:
        if m not in allowed:
            raise ValueError(f"methods: expected some of {allowed} for this scene, got {m!r}")
    frames = (2 if quick else 3) if frames is None else int(frames)
    if frames < 1:
        raise ValueError(f"frames: expected an int >= 1, got {frames!r}")
    faces = scene.load_mesh().num_faces if not scene.objects else 0
    configs = configs or (lambda m: sweep_configs(m, quick=quick, faces=faces))
    runs = [(m, c) for m in methods for c in configs(m)]
    start = time.perf_counter()
    bar = tqdm(total=len(runs) + 1, desc="trade", unit="run", disable=None if progress else True)
    bar.set_postfix_str("reference (truth)")
    ref, ref_mib = run_config(scene, "reference", {}, 1, dtype)
    bar.update(1)
    reference = {"method": "reference", "knobs": jsonable(ref.stats.get("knobs", {})), "setup_s": ref.stats["setup_s"],
                 "frame_s": ref.stats["frame_median_s"], "total_s": ref.stats["total_s"], "peak_mib": ref_mib,
                 "covered_pixels": int(ref.mask.sum())}
    rows = []
    for method, knobs in runs:
        bar.set_postfix_str(f"{method} {knobs}")
        try:
            out, mib = run_config(scene, method, knobs, frames, dtype)
        except ValueError as err:  # a configuration that refuses to build (e.g. memory caps): recorded, not fatal
            rows.append({"method": method, "knobs": dict(knobs), "refused": str(err)})
            bar.update(1)
            continue
        rows.append({"method": method, "knobs": dict(knobs), "setup_s": out.stats["setup_s"],
                     "frame_s": out.stats["frame_median_s"], "total_s": out.stats["total_s"],
                     **image_error(out, ref), "peak_mib": mib, "frames": frames,
                     "stats_knobs": jsonable(out.stats.get("knobs", {}))})
        bar.update(1)
        del out
    bar.close()
    return {"scene": scene.name, "width": scene.camera.width, "height": scene.camera.height,
            "reference": reference, "rows": rows,
            "pareto": [i for i in pareto_front([r if "refused" not in r else {"frame_s": math.inf, "rel_rmse": math.inf}
                                                for r in rows]) if "refused" not in rows[i]],
            "seconds": time.perf_counter() - start}


_COLOURS = {"reference": "black", "splat": "tab:blue", "icdf": "tab:orange", "hybrid": "tab:green",
            "lensch": "tab:red"}


def plot_trade(result: dict, path: Path) -> bool:
    """Error against frame time (log axes, Pareto front marked) and against setup time; False without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    front = [result["rows"][i] for i in result["pareto"]]
    rows = [r for r in result["rows"] if "refused" not in r]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    floor = 1e-4
    for method in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == method]
        for ax, key in zip(axes, ("frame_s", "setup_s")):
            ax.loglog([max(r[key], 1e-3) for r in sel], [max(r["rel_rmse"], floor) for r in sel], "o",
                      color=_COLOURS.get(method), label=method, alpha=0.8)
    axes[0].loglog([r["frame_s"] for r in front], [max(r["rel_rmse"], floor) for r in front], "-", color="grey",
                   lw=2, alpha=0.5, label="Pareto front")
    ref = result["reference"]
    axes[0].axvline(ref["frame_s"], color="black", ls=":",
                    label=f"truth frame {ref['frame_s']:.2f} s (first run: holds any compile)")
    axes[1].axvline(ref["setup_s"] + ref["frame_s"], color="black", ls=":",
                    label=f"truth setup + frame {ref['setup_s'] + ref['frame_s']:.2f} s")
    from matplotlib.ticker import NullFormatter

    for ax, xlabel in zip(axes, ("median frame time (s)", "setup time (s)")):
        ax.xaxis.set_minor_formatter(NullFormatter())  # short ranges: the minor labels overlap
        for t in (0.01, 0.02, 0.05):
            ax.axhline(t, color="grey", lw=0.5, ls="--")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("relative RMSE vs reference")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_title(f"{result['scene']} ({result['width']}x{result['height']}): error vs frame time")
    axes[1].set_title("error vs setup time (build once)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def write_trade(result: dict, out: Path) -> tuple[Path, Path | None]:
    """Write ``out/trade.json`` and ``out/trade.png`` (None when matplotlib is missing)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    js = out / "trade.json"
    js.write_text(json.dumps(jsonable(result), indent=2))
    png = out / "trade.png"
    return js, png if plot_trade(result, png) else None
