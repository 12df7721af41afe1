"""Fit the planner's constants (``torchsss.plan.MODEL``) to the measured trade of the calibration scenes.

Reads ``results/trade/<scene>/trade.json`` of every scene of ``bench_trade.calibration_scenes`` that has one,
computes each scene's closed-form facts (``torchsss.plan.SceneFacts``) and fits, per method, the constants of
``torchsss.plan.predict``: the error constants on log(predicted / measured) with under-prediction weighted 10x
and errors under 0.3% clamped (a plan must not promise an error it misses; over-prediction only costs time), the
time constants on the symmetric
log ratio (with ``--times``; the time constants are otherwise kept: they are set by hand from the same rows,
since a free fit of a few scenes drives some terms to zero). Prints the fitted constants as a Python dict (to paste
into ``MODEL``) and the worst under- and over-prediction per method, and writes ``results/planner_fit.json``.
Also reads the error rows of ``results/planner_v1_rows.json`` to ``planner_v4_rows.json`` (the scenes of the first
four verification runs, which joined the calibration set; see :data:`VERIFICATION_ROWS`); splat's rows come from
``results/splat_calibration_rows.json`` alone where it is here (:data:`SPLAT_ROWS`).

With ``--cv``: leave-one-scene-out cross-validation of the error model. For each calibration scene the error
constants are refitted without it and its rows predicted; per method, the smallest margin (of
``CV_MARGINS``) at which at most ``CV_FALSE_RATE`` of the held-out configurations accepted for a tolerance (1%, 2%,
5%) miss it is the margin :data:`torchsss.plan.MARGINS` should hold (the in-sample margin only shows how well the
constants fit the scenes they were fitted on; the held-out one, how they carry to a scene they have not seen). The
margin with no held-out miss at all is printed too.

Usage::

    python benchmarks/fit_planner.py
    python benchmarks/fit_planner.py --cv      # + leave-one-scene-out margins (results/planner_cv.json)
    python benchmarks/fit_planner.py --times-only   # the setup and frame constants alone (error constants kept)
    python benchmarks/fit_planner.py --cv --methods splat   # one method's fit and margin (the others' kept)
    python benchmarks/fit_planner.py --times-from results/planner_time_rows_main.json \
        results/planner_time_rows_fresh.json
        # the reference's and splat's time constants on verification runs' setup + frame (planner_time_fit.json)

``results/planner_time_rows_{main,fresh}.json`` are the rows the time constants of 2026-11-29 were read from: the
sweep and planned rows of that day's verification runs of the main and fresh sets (one thread, the two side by side,
splat's gather still at its earlier reach rule) with splat's rows replaced by the same configurations re-timed after
``GATHER_REACH`` became 0.01 (the timing of ``bench_splat_paths.py``; its table gives splat's constants).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from torchsss.plan import MODEL, SceneFacts, predict

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_trade import calibration_scenes, scene_key  # noqa: E402

ERROR_KEYS = {
    "reference": ["ref_err_floor", "ref_err_n"],
    "splat": ["splat_floor", "splat_alias", "splat_u_floor", "splat_u_alias", "splat_obj", "splat_obj_p",
              "splat_obj_convex"],
    "icdf": ["icdf_a", "icdf_p", "icdf_floor", "icdf_u", "icdf_q_depth", "icdf_q_spread"],
    "hybrid": ["hybrid_a", "hybrid_p", "hybrid_floor", "hybrid_u", "hybrid_u_floor", "hybrid_q_depth"],
    "lensch": ["lensch_floor", "lensch_texel", "lensch_blend"],
}
#: Frame-time constants per method, fitted in this order: the warm rows' reference, icdf and hybrid frames run
#: in the fused pair sum, whose rate (``fused_t_pair``) the reference rows fix and the estimators reuse.
FRAME_KEYS = {"reference": ["fused_t_pair", "ref_t_src", "ref_t_px"], "splat": ["splat_t", "splat_t_texel", "splat_f0"],
              "icdf": ["icdf_f0"], "hybrid": ["hybrid_f0"], "lensch": ["lensch_t_texel", "lensch_f0"]}
SETUP_KEYS = {"reference": ["ref_s0", "ref_s_src"], "icdf": ["icdf_s0", "icdf_s_face", "icdf_s_texel"],
              "hybrid": ["hybrid_s0"], "lensch": ["lensch_s0", "lensch_s_face", "lensch_s_kernel"]}
#: Errors below this are clamped to it in the fit (every tolerance the planner is asked, 1% and up, is met there).
ERROR_FLOOR = 0.003
#: Weight of an under-predicted error against an over-predicted one.
UNDER = 10.0
EXPONENTS = {"splat_u_floor", "splat_u_alias", "icdf_u", "hybrid_u", "icdf_p", "hybrid_p",
             "icdf_q_spread", "hybrid_u_floor", "icdf_q_depth", "hybrid_q_depth", "splat_obj_p",
             "icdf_face_p"}


#: Methods whose rows with a scene-level ``decimate`` are left out: the camera saw the decimated mesh, which no plan
#: of theirs does today (they decimate through ``source_faces``, the camera on the full mesh). Such rows of a back-lit
#: 20 mm ketchup bunny measured 3.7% at every N (the decimated silhouette), which held the icdf fit's noise term
#: 3-6x over the measured error on every other back-lit scene; they were the hybrid's only held-out false accepts at
#: every margin up to 3 (its unsplit rows use the icdf model). Only the icdf constants were fitted since.
SEEN_FULL = frozenset({"icdf", "hybrid"})


def load_rows() -> list[tuple[object, SceneFacts, dict]]:
    out = []
    splat_rows = HERE / "results" / SPLAT_ROWS
    skip_splat = splat_rows.exists()
    for scene in calibration_scenes(96):
        path = HERE / "results" / "trade" / scene_key(scene) / "trade.json"
        if not path.exists():
            continue
        data = json.loads(path.read_text())
        facts = SceneFacts.from_scene(scene)
        for row in data["rows"]:
            if "refused" in row or (skip_splat and row["method"] == "splat"):
                continue
            knobs = dict(row["knobs"])
            dec = knobs.pop("decimate", None)
            if dec and row["method"] in SEEN_FULL:
                continue
            out.append((scene, facts, {**row, "knobs": knobs, "decimate": dec}))
        out.append((scene, facts, {"method": "reference", "knobs": {"eps": 0.01}, "decimate": None,
                                   "rel_rmse": 0.0, "setup_s": data["reference"]["setup_s"],
                                   "frame_s": data["reference"]["frame_s"], "truth": True}))
    # error rows (no separate setup/frame times) of the scenes of the verification runs, and splat's calibration rows
    from bench_planner import make_scene
    from bench_splat_calibration import scene_of

    for name in (*VERIFICATION_ROWS, SPLAT_ROWS):
        path = HERE / "results" / name
        if not path.exists():
            continue
        splat_only = name == SPLAT_ROWS
        for entry in json.loads(path.read_text())["scenes"]:
            try:
                scene = scene_of(entry["scene"], entry["spec"]) if splat_only else make_scene(entry["scene"],
                                                                                              *entry["spec"])
            except ValueError:  # a shared mesh that is not here
                continue
            facts = SceneFacts.from_scene(scene)
            for row in entry["rows"]:
                if (row["method"] == "splat" and skip_splat and not splat_only) or (splat_only and
                                                                                    row["method"] != "splat"):
                    continue
                knobs = dict(row["knobs"])
                knobs.pop("flux", None)
                dec = knobs.pop("decimate", None)
                if dec and row["method"] in SEEN_FULL:
                    continue
                out.append((scene, facts, {**row, "knobs": knobs, "decimate": dec, "errors_only": True}))
    return out


#: Error rows of earlier verification runs whose scenes joined the calibration set: the first run's three scenes
#: (every method), the second run's nine (2026-11-26; the splat error model was refitted with them on 2026-11-27),
#: the third and fourth runs' nine each (``bench_planner.VERIFICATION`` and ``FRESH``, 2026-11-27: the reference's
#: and splat's error constants were refitted with them; the other methods' constants predate them).
VERIFICATION_ROWS = ("planner_v1_rows.json", "planner_v2_rows.json", "planner_v3_rows.json",
                     "planner_v4_rows.json")
#: Splat's rows re-measured on the scenes of :data:`VERIFICATION_ROWS` and of the calibration trades (96 x 96) with the
#: current splat renderer, at every configuration it is planned at (``bench_splat_calibration.py``: oversample 1, 2,
#: 4 and 8; since 2026-11-28 its light view's flux follows the shading normals, ``torchsss.geometry.shading_flux``).
#: Where this file is here, splat is fitted to it alone: the other files' splat rows (and the calibration trades')
#: were rendered by the earlier splat.
SPLAT_ROWS = "splat_calibration_rows.json"


#: The time constants ``--times-from`` fits, per method, on a verification run's setup + one frame (the splat
#: and reference setups' constant parts are kept: the rows do not separate them from the frame).
TOTAL_KEYS = {"reference": ["fused_t_pair", "ref_t_src", "ref_t_px"],
              "splat": ["splat_t_gather", "splat_t_texel", "splat_f0"],
              "icdf": ["icdf_s0", "icdf_s_face", "icdf_face_p", "icdf_f0"], "hybrid": ["hybrid_s0", "hybrid_f0"]}


def load_time_rows(paths: list[Path]) -> list[tuple[object, SceneFacts, dict]]:
    """The sweep and planned rows of verification runs (``bench_planner.py``'s ``<name>_rows.json``) for a time fit.

    Each row's ``time_s`` is its setup and one frame, measured warm: the run's truth compiled the plain pair sum
    first, and splat's truncated gather is compiled by the first splat row that asks for it (:data:`WARM_ALL`: a
    run's first scene's splat rows before that row are predicted as compiled too).
    """
    from bench_planner import SETS, make_scene

    specs = {name: spec for scenes in SETS.values() for name, spec in scenes.items()}
    out = []
    for path in paths:
        for name, rows in json.loads(Path(path).read_text()).items():
            scene = make_scene(name, *specs[name])
            facts = SceneFacts.from_scene(scene)
            for row in rows:
                if row["kind"] == "truth":
                    continue
                knobs = dict(row["knobs"])
                dec = knobs.pop("decimate", None)
                out.append((scene, facts, {**row, "knobs": knobs, "decimate": dec, "set": Path(path).name}))
    return out


def times_from(paths: list[Path]) -> dict:
    """Fit :data:`TOTAL_KEYS` to verification rows; print predicted / measured per method and file."""
    rows = load_time_rows(paths)
    fitted: dict[str, float] = {}
    for method, keys in TOTAL_KEYS.items():
        mine = [r for r in rows if r[2]["method"] == method]
        fitted.update(fit(mine, keys, "time_s", asymmetric=False, base=fitted, warm=WARM_ALL))
    model = {**MODEL, **fitted}
    report = {}
    for label, m in (("before", MODEL), ("after", model)):
        for method in ERROR_KEYS:  # the other methods' rows are reported, not fitted (their frames share the rate)
            for name in sorted({r[2]["set"] for r in rows}):
                q = []
                for scene, facts, row in rows:
                    if row["method"] == method and row["set"] == name:
                        p = _pred(row, facts, scene, m, WARM_ALL)
                        q.append((p["setup_s"] + p["frame_s"]) / row["time_s"])
                if q:
                    q = sorted(q)
                    report[f"{label} {method} {name}"] = [round(q[len(q) // 10], 3), round(float(np.median(q)), 3),
                                                          round(q[(9 * len(q)) // 10], 3), len(q)]
                    print(f"{label:6s} {method:9s} {name:28s} predicted/measured p10, median, p90, rows: "
                          f"{report[f'{label} {method} {name}']}")
    print("MODEL updates:")
    print(json.dumps({k: float(f"{v:.3g}") for k, v in fitted.items()}, indent=1))
    return {"fitted": fitted, "predicted_over_measured": report}


def _methods() -> list[str]:
    """The methods of ``--methods m1 m2 ...`` (default: all)."""
    if "--methods" not in sys.argv:
        return list(ERROR_KEYS)
    i = sys.argv.index("--methods") + 1
    chosen = []
    while i < len(sys.argv) and not sys.argv[i].startswith("--"):
        chosen.append(sys.argv[i])
        i += 1
    unknown = [m for m in chosen if m not in ERROR_KEYS]
    if unknown or not chosen:
        raise SystemExit(f"--methods: expected some of {list(ERROR_KEYS)}, got {chosen}")
    return chosen


#: The trade rows are measured warm: the truth render compiles the fused pair sum first, and a row's frame time is
#: the median of its frames (a hybrid row's split-kernel compile falls in its first frame).
WARM = frozenset({"plain", "split"})
#: Every variant compiled (a verification run's rows after its first splat gather).
WARM_ALL = frozenset({"plain", "split", "truncated"})


def _truth(row: dict) -> bool:
    """A truth render (a calibration trade's reference, or a verification run's ``kind: truth`` row): error 0."""
    return bool(row.get("truth")) or row.get("kind") == "truth"


def _pred(row, facts, scene, model, warm: frozenset[str] = WARM) -> dict:
    out = predict(row["method"], row["knobs"], facts, scene.material, decimate=row["decimate"], model=model,
                  warm=warm)
    # the trades time the setup without the first frame's material precompute (Lensch's ``first_s``)
    return {**out, "setup_s": out["setup_s"] - out.get("first_s", 0.0)}


def fit(rows, keys: list[str], target: str, asymmetric: bool, base: dict | None = None,
        warm: frozenset[str] = WARM) -> dict:
    base = {**MODEL, **(base or {})}  # the constants held fixed (earlier fits of this run)
    x0 = np.array([math.log(max(base[k], 1e-12)) if k not in EXPONENTS else base[k] for k in keys])

    def model_of(x):
        return {k: (float(v) if k in EXPONENTS else math.exp(v)) for k, v in zip(keys, x)}

    def loss(x):
        m = {**base, **model_of(x)}
        total = 0.0
        for scene, facts, row in rows:
            if target not in row:
                continue
            measured = row[target]
            if _truth(row):  # error 0 by definition; its one frame holds the process's cold compile
                continue
            if target == "rel_rmse" and measured <= 0:
                continue
            p = _pred(row, facts, scene, m, warm)
            predicted = p["setup_s"] + p["frame_s"] if target == "time_s" else p[{"rel_rmse": "error"}.get(target,
                                                                                                         target)]
            if target == "rel_rmse":  # below 0.3% every tolerance (1% and up) is met: the value does not matter
                predicted, measured = max(predicted, ERROR_FLOOR), max(measured, ERROR_FLOOR)
            if predicted <= 0 or measured <= 0:
                continue
            d = math.log(predicted / measured)
            total += (UNDER * d * d if d < 0 else d * d) if asymmetric else d * d
        return total

    bounds = [(0.0, 3.0) if k in EXPONENTS else (math.log(1e-4 * base[k]), math.log(1e2 * base[k]))
              for k in keys]
    x0 = np.clip(x0, [b[0] for b in bounds], [b[1] for b in bounds])
    res = minimize(loss, x0, method="Powell", bounds=bounds, options={"maxiter": 4000, "xtol": 1e-4})
    return model_of(res.x)


def main() -> None:
    if "--times-from" in sys.argv:
        i = sys.argv.index("--times-from") + 1
        paths = []
        while i < len(sys.argv) and not sys.argv[i].startswith("--"):
            paths.append(Path(sys.argv[i]))
            i += 1
        result = times_from(paths)
        (HERE / "results" / "planner_time_fit.json").write_text(json.dumps({"rows": [str(p) for p in paths],
                                                                             **result}, indent=1))
        return
    rows = load_rows()
    scenes = sorted({scene.name for scene, _, _ in rows})
    print(f"{len(rows)} rows from {len(scenes)} scenes: {scenes}")
    fitted: dict[str, float] = {}
    for method in _methods():
        mine = [r for r in rows if r[2]["method"] == method]
        if not mine:
            continue
        if "--times-only" not in sys.argv:
            fitted.update(fit(mine, ERROR_KEYS[method], "rel_rmse", asymmetric=True, base=fitted))
        if "--times" in sys.argv or "--times-only" in sys.argv:
            fitted.update(fit(mine, FRAME_KEYS[method], "frame_s", asymmetric=False, base=fitted))
            if method in SETUP_KEYS:
                fitted.update(fit(mine, SETUP_KEYS[method], "setup_s", asymmetric=False, base=fitted))
    model = {**MODEL, **fitted}
    report = {}
    for method in _methods():
        ratios = {"error": [], "frame_s": [], "setup_s": []}
        for scene, facts, row in rows:
            if row["method"] != method:
                continue
            p = _pred(row, facts, scene, model)
            if not _truth(row) and row["rel_rmse"] > ERROR_FLOOR:
                ratios["error"].append(max(p["error"], ERROR_FLOOR) / row["rel_rmse"])
            if "frame_s" in row:
                ratios["frame_s"].append(p["frame_s"] / row["frame_s"])
                ratios["setup_s"].append(p["setup_s"] / max(row["setup_s"], 1e-3))
        report[method] = {k: [round(min(v), 3), round(float(np.median(v)), 3), round(max(v), 3)]
                          for k, v in ratios.items() if v}
        print(f"{method:10s} predicted/measured (min, median, max): {report[method]}")
    print("margin: false accepts (predicted * margin <= t < measured) / accepts over the rows and t = 1%, 2%, 5%")
    margins = {}
    for margin in (1.0, 1.1, 1.25, 1.5, 1.75, 2.0):
        bad = acc = 0
        for scene, facts, row in rows:
            if _truth(row) or row["method"] not in _methods():
                continue
            p = _pred(row, facts, scene, model)["error"]
            for t in (0.01, 0.02, 0.05):
                if p * margin <= t:
                    acc += 1
                    bad += row["rel_rmse"] > t
        margins[margin] = [bad, acc]
        print(f"  {margin}: {bad} / {acc}")
    report["margins"] = margins
    print("MODEL updates:")
    print(json.dumps({k: float(f"{v:.3g}") for k, v in fitted.items()}, indent=1))
    (HERE / "results" / "planner_fit.json").write_text(json.dumps(
        {"scenes": scenes, "fitted": fitted, "predicted_over_measured": report}, indent=1))


CV_MARGINS = (1.0, 1.1, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0)
#: The held-out false-accept rate a margin may leave (the planner's goal: 90% of plans within their tolerance).
CV_FALSE_RATE = 0.05


def cross_validate(rows) -> dict:
    """Leave-one-scene-out margins per method (see the module docstring)."""
    scenes = sorted({scene.name for scene, _, _ in rows})
    path = HERE / "results" / "planner_cv.json"
    out = json.loads(path.read_text()) if path.exists() else {}  # the methods not run keep their entries
    for method in _methods():
        mine = [r for r in rows if r[2]["method"] == method]
        bad = {m: 0 for m in CV_MARGINS}
        acc = {m: 0 for m in CV_MARGINS}
        worst = []
        for held in scenes:
            train = [r for r in mine if r[0].name != held]
            test = [r for r in mine if r[0].name == held and not _truth(r[2])]
            if not test or not train:
                continue
            model = {**MODEL, **fit(train, ERROR_KEYS[method], "rel_rmse", asymmetric=True)}
            for scene, facts, row in test:
                p = _pred(row, facts, scene, model)["error"]
                for t in (0.01, 0.02, 0.05):
                    if row["rel_rmse"] > t:
                        worst.append(row["rel_rmse"] / max(p, 1e-12))
                    for m in CV_MARGINS:
                        if p * m <= t:
                            acc[m] += 1
                            bad[m] += row["rel_rmse"] > t
        margin = next((m for m in CV_MARGINS if bad[m] <= CV_FALSE_RATE * acc[m]), None)
        strict = next((m for m in CV_MARGINS if bad[m] == 0), None)
        out[method] = {"margin": margin, "margin_no_false_accept": strict,
                       "false_accepts": {str(m): [bad[m], acc[m]] for m in CV_MARGINS}}
        print(f"{method:10s} held-out false accepts / accepts by margin: "
              f"{ {m: (bad[m], acc[m]) for m in CV_MARGINS} } -> margin {margin} (none false: {strict})", flush=True)
    path.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    if "--cv" in sys.argv:
        cross_validate(load_rows())
    else:
        main()
