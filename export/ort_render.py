"""Render a frame from saved G-buffers with ONNX Runtime only (no torch).

Usage::

    python -m torchsss render default --method splat --save-gbuffers frame.npz   # with torch, once
    python export/ort_render.py frame.npz --out frame.exr                        # numpy + onnxruntime (+ OpenEXR)

The ``.npz`` (``torchsss.export.frames.save_gbuffers``) holds the exported frame graph (``model``: the ONNX
file's bytes, with the material as inputs), the graph input names (``input_names``), one array per input and,
for checks, the library's own radiance of the frame (``radiance``). Material inputs can be overridden
(``--sigma-a``, ``--sigma-s-prime``, ``--eta``: the splat's truncation radius ``r_max`` is then kept, so a
material with a longer profile needs a new save). Prints the relative RMSE against the stored radiance. Exit
status 0, 1 when the splat graph reports truncated splats or the image differs from the stored radiance by more
than ``--check`` (relative RMSE), 2 for usage errors.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort


def write_exr(path: Path, image: np.ndarray) -> Path:
    """Write a (3, H, W) float32 image as an RGB OpenEXR file (ZIP), as ``torchsss.io.write_exr`` does."""
    import OpenEXR

    channels = {n: np.ascontiguousarray(image[i].astype(np.float32)) for i, n in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path.parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))
    return path


def rel_rmse(a: np.ndarray, ref: np.ndarray) -> float:
    """sqrt(mean((a - ref)^2)) / sqrt(mean(ref^2)), in float64."""
    a, ref = a.astype(np.float64), ref.astype(np.float64)
    den = np.sqrt(np.mean(ref * ref))
    return float(np.sqrt(np.mean((a - ref) ** 2)) / den) if den > 0 else float(np.abs(a).max())


def render(gbuffers: Path, threads: int = 1, overrides: dict | None = None) -> tuple[np.ndarray, dict]:
    """Run the frame graph of ``gbuffers``; returns the (3, H, W) radiance and a dict of facts."""
    data = np.load(gbuffers, allow_pickle=False)
    names = [str(n) for n in data["input_names"]]
    meta = json.loads(str(data["meta"]))
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    t0 = time.perf_counter()
    session = ort.InferenceSession(data["model"].tobytes(), sess_options=opts, providers=["CPUExecutionProvider"])
    feed = {n: data[n] for n in names}
    for k, v in (overrides or {}).items():
        if v is not None:
            feed[k] = np.asarray(v, dtype=np.float32).reshape(feed[k].shape)
    t1 = time.perf_counter()
    out = session.run(None, feed)
    t2 = time.perf_counter()
    facts = {**meta, "session_s": t1 - t0, "run_s": t2 - t1}
    if len(out) > 1:
        facts["truncated_splats"] = int(np.asarray(out[1]).sum())
    if "radiance" in data:
        facts["rel_rmse_vs_library"] = rel_rmse(out[0][0], data["radiance"][0])
    return out[0][0], facts


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ort_render.py", description="Render saved G-buffers with ONNX Runtime.")
    p.add_argument("gbuffers", type=Path, help="the .npz written by `python -m torchsss render ... --save-gbuffers`")
    p.add_argument("--out", type=Path, default=Path("ort_render.exr"), help="output EXR (default ort_render.exr)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads (default 1; 0 = auto)")
    p.add_argument("--check", type=float, default=None,
                   help="fail when the relative RMSE against the stored library radiance exceeds this")
    for flag in ("--sigma-a", "--sigma-s-prime"):
        p.add_argument(flag, type=float, nargs=3, default=None, metavar=("R", "G", "B"),
                       help=f"override the material's {flag[2:].replace('-', '_')} (mm^-1)")
    p.add_argument("--eta", type=float, default=None, help="override the material's relative index of refraction")
    ns = p.parse_args(argv)
    if not ns.gbuffers.is_file():
        p.error(f"GBUFFERS: expected an existing .npz, got {str(ns.gbuffers)!r}")
    if ns.threads < 0:
        p.error(f"--threads: expected an int >= 0, got {ns.threads}")
    overrides = {"sigma_a": ns.sigma_a, "sigma_s_prime": ns.sigma_s_prime, "eta": ns.eta}
    image, facts = render(ns.gbuffers, ns.threads, overrides)
    write_exr(ns.out, image)
    print(f"wrote {ns.out} ({facts['method']}, {facts['width']}x{facts['height']}): onnxruntime session "
          f"{facts['session_s']:.2f} s, frame {1e3 * facts['run_s']:.1f} ms")
    ok = True
    if "truncated_splats" in facts:
        n = facts["truncated_splats"]
        print(f"truncated splats: {n}" + (" (the window is too small for this frame: light was lost)" if n else ""))
        ok &= n == 0
    if "rel_rmse_vs_library" in facts and not any(v is not None for v in overrides.values()):
        err = facts["rel_rmse_vs_library"]
        print(f"relative RMSE against the library's render of this frame: {err:.3e}")
        if ns.check is not None:
            ok &= err <= ns.check
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
