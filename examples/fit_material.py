"""Inverse rendering of a homogeneous translucent material: sigma_a, sigma_s' (and eta) from images.

Recovers sigma_a and sigma_s' per channel (and optionally eta) through a fast differentiable renderer (issue 18).

Usage::

    python examples/fit_material.py [SCENE] --target-material potato --json out/fit/potato.json
    python examples/fit_material.py SCENE --targets view0.exr view1.exr view2.exr view3.exr --json out.json

``SCENE`` is a scene file or ``default`` (the shipped spot, 40 mm). The views are the scene's camera orbited about
its ``up`` axis through the target by ``360 k / V`` degrees (k = 0..V-1), the scene's lights fixed, so that every
view sees the object lit from another side (back-lit, side-lit, front-lit): ``--views V`` with
``--target-material`` (the targets are rendered with the all-pairs reference at ``--size``), or one view per
``--targets`` EXR file (linear radiance as ``python -m torchsss render`` writes it, view k = the k-th file; its
resolution is the camera's).

**Method.** The fit renders through ``splat`` (Shah's image-space splatting) at ``--eps`` 0.01 and ``--oversample``
1 by default (window form), or with the splat budget :func:`torchsss.plan.plan` picks for ``--tolerance`` among the
splat configurations (``frames`` = steps x views; at 5% it picks eps 0.003, oversample 2, 3-4x the cost per step).
Why splat and not the planner's unrestricted pick or Lensch: at the small images a fit uses, the planner's
cheapest configuration is a coarse reference (its speed comes from the fused all-pairs kernel, which runs in
inference only: under autograd it is the eager integrator) and fitting with the targets' own integrator would be
an inverse crime; Lensch's per-frame cost under autograd re-evaluates its kernels and throughput from the stored
distances (measured on the default scene at 48 x 48, atlas 128: 77 s forward + 79 s backward per view against
1.1 s + 0.8 s for splat). ``--method`` takes any differentiable method (``splat``, ``lensch``, ``icdf``,
``hybrid``, ``reference``) for comparison.

**Solver.** ``--optimizer lm`` (default): Levenberg-Marquardt (``fit_lm.py``; the gradient by autograd through the
fast method, the Gauss-Newton matrix from central differences of its renders, one pair per per-channel parameter
group) inside a defect-correction loop: each outer iteration renders the reference once (forward only) at the
current material and fits the fast render plus that difference to the targets, so the fixed point is the material
whose *reference* image matches the targets and the fast method only supplies the derivatives (``--no-correct``
drops the correction). The targets are rendered at a finer sample spacing than the correction's
(:func:`target_spacing`), so the fit does not share their quadrature. ``--optimizer adam``: Adam with a cosine
decay, the renderer rebuilt every ``--rebuild-every`` steps. Measured (``benchmarks/results/fit.md``, 4 presets x 2
sizes): every coefficient within 3.1% in 8-36 s with ``lm``; up to 37.5% off without the correction and up to 197%
after 60 Adam steps.

**Parameterisation.** The optimised parameters are, per channel, :math:`\\log\\sigma_{tr}` (the effective transport
coefficient :math:`\\sqrt{3\\sigma_a\\sigma_t'}`, which sets how fast light falls off across the surface) and
:math:`\\log(\\sigma_s'/\\sigma_a)` (the log-odds of the reduced albedo :math:`\\alpha'`, which sets how bright the
object is), and :math:`\\log\\eta` (:class:`LogDipoleMaterial`: the library's :class:`~torchsss.modules.DipoleMaterial`
with these parameters in place of the softplus ones; sigma_a and sigma_s' are derived). In log space one Adam step
changes each quantity by about the same *relative* amount whatever its magnitude (the potato's absorption spans
0.0024-0.12 mm^-1). Fitting :math:`\\log\\sigma_a` and :math:`\\log\\sigma_s'` directly works too, but the images
determine falloff and brightness, and along the valley that keeps both nearly fixed :math:`\\log\\sigma_a` and
:math:`\\log\\sigma_s'` move together: measured on the default scene (potato, 3 views at 48 x 48, 60 Adam steps at
0.1), that parameterisation ended at a loss of 2.8e-2 with red and green sigma_a 41% and 71% off, still crawling
along the valley. The loss is the mean over views of the relative squared error
:math:`\\sum (L - L^*)^2 / \\sum L^{*2}` over the pixels; the learning rate decays on a cosine to 1/20 of ``--lr``.

**Identifiability.** What the images determine, and what they do not:

- *Absolute scale.* With the lights' intensities known (the scene file), the absolute radiance fixes the total
  diffuse reflectance :math:`R_d` (a function of the reduced albedo :math:`\\alpha' = \\sigma_s'/(\\sigma_a +
  \\sigma_s')`) and the falloff of the light across the surface fixes :math:`\\sigma_{tr} = \\sqrt{3\\sigma_a
  \\sigma_t'}`; together they determine sigma_a and sigma_s' per channel. From EXR targets of unknown exposure (or
  lights of unknown intensity) only the falloff is left: :math:`\\sigma_{tr}` is determined, the albedo is not
  (scaling the light by k and changing :math:`\\alpha'` so that :math:`R_d` scales by 1/k gives nearly the same
  image), so sigma_a and sigma_s' trade off along a curve of constant :math:`\\sigma_{tr}`.
- *Scattering length below a pixel.* :math:`1/\\sigma_t'` (about 1.4 mm for potato) only shows through the
  dipole's near field; at 48 x 48 a pixel of the default scene spans about 0.8 mm, so sigma_s' is determined mostly
  through :math:`\\alpha'` and :math:`\\sigma_{tr}`, not through the shape of the near field.
- *Weak absorption.* When :math:`\\sigma_a \\ll \\sigma_s'` (potato's red and green: 0.0024 and 0.009 mm^-1 against
  0.7) the image depends on sigma_a only weakly, and less the larger :math:`1/\\sigma_{tr}` (14 mm in red) is
  against the object (the light leaves before it is absorbed). ``--sensitivity`` measures it: on the default scene
  (potato, 3 views at 48 x 48) +10% of sigma_a changes the reference images by 0.72% (red), 1.6% (green) and 4.9%
  (blue) in that channel, +10% of sigma_s' by 3.8%, 4.0% and 6.1%.
- *The fast method's own error* (without the correction, ``--no-correct`` or Adam). The fitted parameters absorb the
  renderer's error against the reference: at the true potato, splat (eps 0.01) is 4.2%, 4.9%, 7.4% off per channel
  (relative L2 over the views) at oversample 1 and 1.65%, 1.8%, 2.5% at oversample 2. A coefficient whose 10% change
  moves its images by less than that error (potato's red sigma_a: 0.72% against 1.65%) cannot be recovered to 10%
  through splat at that budget: the fit matches the splat error by moving it. The same in red on the spot at 20 mm
  (``benchmarks/results/fit.md``: red sigma_a 236% off, the other coefficients 0-26%). The reference correction
  removes this error from the fixed point (potato's red sigma_a within 0.2-0.4% with ``lm``).
- *eta.* eta enters the Fresnel transmittances in and out and the dipole's boundary term A; its effect is close to
  a change of overall brightness, which trades off against the albedo, so ``--fit-eta`` is off by default (the
  fit holds eta at the target's, 1.3 for all Jensen presets).

Outputs (``--out DIR``, default beside ``--json``): ``loss.png`` (the loss curve), ``side_by_side.png`` (rows:
views; columns: target, initial, fitted; one exposure per row, from the target) and the JSON (``--json``): the
method and its knobs, the target, initial and fitted parameters, the per-channel relative errors, the loss
history and the times.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import torch
from torch import Tensor, nn

import torchsss
from torchsss.geometry import Camera
from torchsss.io import read_exr, tonemap, write_exr, write_png
from torchsss.modules import DipoleMaterial
from torchsss.physics.materials import Material
from torchsss.pipelines import build
from torchsss.scene import Scene, default_scene_path, load_scene

__all__ = ["LogDipoleMaterial", "fit", "load_fit_scene", "orbit_cameras", "relative_errors", "render_targets",
           "target_spacing", "view_loss"]

DIFFERENTIABLE = ("splat", "lensch", "icdf", "hybrid", "reference")


class LogDipoleMaterial(DipoleMaterial):
    """The dipole parameterised by :math:`\\log\\sigma_{tr}`, :math:`\\log(\\sigma_s'/\\sigma_a)`, :math:`\\log\\eta`.

    A :class:`~torchsss.modules.DipoleMaterial` (module docstring, "Parameterisation"):

    Parameters ``log_sigma_tr`` and ``log_albedo_ratio`` :math:`(C,)` and ``raw_eta`` (holding :math:`\\log\\eta`)
    replace the base class's softplus parameters; ``sigma_a``, ``sigma_s_prime`` and ``eta`` are derived from them,
    so the module follows the profile contract unchanged and renders through every method:
    :math:`\\rho = e^{b}`, :math:`\\sigma_t' = \\sigma_{tr}\\sqrt{(1 + \\rho)/3}`,
    :math:`\\sigma_a = \\sigma_t'/(1 + \\rho)`, :math:`\\sigma_s' = \\rho\\,\\sigma_a`.

    Examples:
        >>> m = LogDipoleMaterial([0.01, 0.1, 1.0], [1.0, 1.0, 1.0], 1.3, dtype=torch.float64)
        >>> [round(v, 6) for v in m.sigma_a.tolist()], [round(v, 6) for v in m.sigma_s_prime.tolist()]
        ([0.01, 0.1, 1.0], [1.0, 1.0, 1.0])
        >>> sorted(n for n, _ in m.named_parameters())
        ['log_albedo_ratio', 'log_sigma_tr', 'raw_eta']
    """

    def __init__(self, sigma_a, sigma_s_prime, eta=1.3, **kwargs) -> None:
        super().__init__(sigma_a, sigma_s_prime, eta, **kwargs)
        with torch.no_grad():  # the base class validated the values
            sa, ss, et = (self._as(v) for v in (sigma_a, sigma_s_prime, eta))
            sa = sa.reshape(self.raw_sigma_a.shape).clamp_min(1e-12)
            ss = ss.reshape(sa.shape).clamp_min(1e-12)
            self.raw_eta.copy_(torch.log(et.reshape(self.raw_eta.shape)))
        del self.raw_sigma_a, self.raw_sigma_s_prime
        self.log_sigma_tr = nn.Parameter(0.5 * torch.log(3.0 * sa * (sa + ss)))
        self.log_albedo_ratio = nn.Parameter(torch.log(ss / sa))

    def _as(self, value) -> Tensor:
        p = self.raw_eta
        return torch.as_tensor(value, dtype=p.dtype).to(p.device)

    @classmethod
    def from_material(cls, material: Material, **kwargs) -> LogDipoleMaterial:
        """From a :class:`~torchsss.physics.Material` record."""
        return cls(list(material.sigma_a), list(material.sigma_s_prime), material.eta, **kwargs)

    @property
    def channels(self) -> int:
        """Number of colour channels C."""
        return max(self.log_sigma_tr.numel(), 1)

    @property
    def sigma_t_prime(self) -> Tensor:
        """Reduced extinction :math:`\\sigma_a + \\sigma_s'` (mm^-1), :math:`(C,)`."""
        return torch.exp(self.log_sigma_tr) * torch.sqrt((1.0 + torch.exp(self.log_albedo_ratio)) / 3.0)

    @property
    def sigma_a(self) -> Tensor:
        """Absorption coefficient (mm^-1), :math:`(C,)`."""
        return self.sigma_t_prime / (1.0 + torch.exp(self.log_albedo_ratio))

    @property
    def sigma_s_prime(self) -> Tensor:
        """Reduced scattering coefficient (mm^-1), :math:`(C,)`."""
        return self.sigma_a * torch.exp(self.log_albedo_ratio)

    @property
    def eta(self) -> Tensor:
        """Relative index of refraction."""
        return torch.exp(self.raw_eta)


def load_fit_scene(scene: str, size: int | None = None) -> Scene:
    """A scene file or ``"default"``, with the camera at ``size`` x ``size`` pixels when given."""
    s = load_scene(default_scene_path() if scene == "default" else scene)
    if size is not None:
        s = dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=int(size), height=int(size)))
    return s


def orbit_cameras(camera: Camera, views: int) -> list[Camera]:
    """The camera orbited about its ``up`` axis through ``target`` by :math:`360 k / V` degrees, k = 0..V-1."""
    eye, target = torch.tensor(camera.eye, dtype=torch.float64), torch.tensor(camera.target, dtype=torch.float64)
    up = torch.tensor(camera.up, dtype=torch.float64)
    up = up / up.norm()
    out = []
    for k in range(views):
        a = 2.0 * math.pi * k / views
        v = eye - target
        # Rodrigues' rotation of v about up by a
        r = v * math.cos(a) + torch.linalg.cross(up, v) * math.sin(a) + up * (up @ v) * (1.0 - math.cos(a))
        out.append(dataclasses.replace(camera, eye=tuple(float(x) for x in target + r)))
    return out


def target_spacing(mesh, material: Material, eps: float = 1e-3) -> float:
    """The sample spacing (mm) of independent targets: the reference's at ``eps``, and at most half the median edge.

    The reference places :math:`\\lceil \\ell / s\\rceil^2` samples on a face whose longest edge is :math:`\\ell`, so
    on a finely tessellated mesh every spacing above the edge lengths gives the same samples (one per face). Half
    the median longest edge puts at least 4 samples on most faces: the targets' quadrature differs from that of the
    reference at its default spacing, which the fit's correction renders (fitting with the targets' own
    discretisation would recover them exactly, whatever the method: an inverse crime).
    """
    from torchsss.pipelines.reference import default_spacing

    tri = mesh.triangles()
    longest = torch.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], 1).norm(dim=-1)
    return min(default_spacing(material, mesh, eps), 0.5 * float(longest.amax(1).median()))


def render_targets(scene: Scene, mesh, material: Material, cameras: list[Camera], **knobs) -> list[Tensor]:
    """Images :math:`(1, 3, H, W)` rendered with the all-pairs reference (one build, one frame per view).

    ``knobs`` go to the reference (e.g. ``spacing_mm=target_spacing(mesh, material)`` for independent targets).
    """
    ref = build("reference", mesh, material, **knobs)
    with torch.no_grad():
        return [ref.render(list(scene.lights), cam).radiance for cam in cameras]


def view_loss(image: Tensor, target: Tensor) -> Tensor:
    """Relative squared error :math:`\\sum (L - L^*)^2 / \\sum L^{*2}` of one view."""
    return ((image - target) ** 2).sum() / (target**2).sum().clamp_min(1e-30)


def relative_errors(fitted: dict, target: Material) -> dict:
    """Per-channel relative errors of the fitted coefficients against the target record."""
    out = {}
    for key in ("sigma_a", "sigma_s_prime"):
        t = getattr(target, key)
        out[key] = [abs(f - v) / v if v > 0 else abs(f - v) for f, v in zip(fitted[key], t)]
    out["eta"] = abs(fitted["eta"] - target.eta) / target.eta
    return out


def sensitivity(scene: Scene, mesh, target: Material, cameras: list[Camera], targets: list[Tensor], method: str,
                knobs: dict, dtype: torch.dtype = torch.float32, step: float = 0.1) -> dict:
    """What the images can tell apart: per channel, the image change for +10% of a coefficient vs the method's error.

    The relative change of the reference images when one coefficient grows by ``step`` (10%), against the fit
    method's own error at the target material.

    A coefficient whose 10% change moves its channel's images by less than the fast method's error there cannot be
    recovered to 10% through that method (the renderer's bias can be matched by moving it instead).

    Returns:
        ``{"sigma_a": [...], "sigma_s_prime": [...]}`` (relative L2 change of channel c's pixels over all views for
        +``step`` on channel c) and ``"method_error"`` (relative L2 error of ``method`` against the reference, per
        channel, at the target material).
    """
    def rel(a: Tensor, b: Tensor, c: int) -> float:
        return float((a[:, c] - b[:, c]).norm() / b[:, c].norm().clamp_min(1e-30))

    base = torch.cat(targets)
    out: dict = {}
    with torch.no_grad():
        for key in ("sigma_a", "sigma_s_prime"):
            out[key] = []
            for c in range(3):
                d = {"sigma_a": list(target.sigma_a), "sigma_s_prime": list(target.sigma_s_prime), "eta": target.eta}
                d[key] = [v * (1.0 + step) if i == c else v for i, v in enumerate(d[key])]
                ref = build("reference", mesh, Material.from_json(d), dtype=dtype)
                img = torch.cat([ref.render(list(scene.lights), cam).radiance for cam in cameras])
                out[key].append(rel(img, base, c))
        fast = build(method, mesh, target, dtype=dtype, **knobs)
        img = torch.cat([fast.render(list(scene.lights), cam).radiance for cam in cameras])
        out["method_error"] = [rel(img, base, c) for c in range(3)]
    out["step"] = step
    return out


def _params(m: DipoleMaterial) -> dict:
    return {"sigma_a": [float(v) for v in m.sigma_a.detach()], "sigma_s_prime": [float(v) for v in
                                                                                   m.sigma_s_prime.detach()],
            "eta": float(m.eta.detach().reshape(-1)[0])}


def fit(renderer, lights, cameras: list[Camera], targets: list[Tensor], *, steps: int, lr: float, fit_eta: bool,
        progress: bool = True, loss_of_views=None, rebuild=None, rebuild_every: int = 10) -> dict:
    """Adam on the renderer's material (a :class:`LogDipoleMaterial`): the full batch of views every step.

    Args:
        renderer: a differentiable renderer whose ``material`` is a :class:`LogDipoleMaterial`.
        lights: the scene's lights.
        cameras: one camera per view.
        targets: one :math:`(1, 3, H, W)` image per view.
        steps: Adam steps.
        lr: Adam learning rate (in log space: about the relative change per step).
        fit_eta: optimise eta too (else it stays at its initial value).
        progress: a tqdm progress bar.
        loss_of_views: a callable ``(renderer, lights, cameras, targets) -> loss tensor`` replacing the mean of
            :func:`view_loss` over the views (the data-parallel example's hook); it calls ``backward`` itself.
        rebuild: a callable returning a new renderer of the same material module, called every
            ``rebuild_every`` steps: the knobs a renderer plans from its material at build time (splat's
            :math:`r_{max}` and light-view grid, Lensch's kernels) must follow the material as it moves, or the
            fit converges to the material whose truncated render matches (measured on potato from sigma_a = 0.05:
            a splat r_max planned for the initial material cut the far field and left sigma_a 36-56% off).
        rebuild_every: steps between rebuilds.

    Returns:
        ``{"loss": [...], "params": {...}, "trace": [...], "rebuilds": n, "renderer": the last renderer}``: the loss
        before every step, the parameters after the last, and per step the parameters after it with the wall time
        since the start (``{"sigma_a", "sigma_s_prime", "eta", "t_s"}``).
    """
    mat = renderer.material
    params = [mat.log_sigma_tr, mat.log_albedo_ratio] + ([mat.raw_eta] if fit_eta else [])
    mat.raw_eta.requires_grad_(fit_eta)
    opt = torch.optim.Adam(params, lr=lr)
    # cosine decay to lr / 20: large steps along the valley first, then settle
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * k / steps)))
    history = []
    bar = range(steps)
    if progress:
        from tqdm import tqdm

        bar = tqdm(bar, desc=f"fit ({renderer.method})", unit="step", file=sys.stdout)
    rebuilds, trace, t0 = 0, [], time.perf_counter()
    with torchsss.validation(False):
        for step in bar:
            if rebuild is not None and step > 0 and step % rebuild_every == 0:
                renderer, rebuilds = rebuild(), rebuilds + 1
            opt.zero_grad(set_to_none=True)
            if loss_of_views is None:
                loss = sum(view_loss(renderer.render(lights, cam).radiance, t)
                           for cam, t in zip(cameras, targets)) / len(cameras)
                loss.backward()
            else:
                loss = loss_of_views(renderer, lights, cameras, targets)
            opt.step()
            sched.step()
            history.append(float(loss.detach()))
            trace.append({**_params(mat), "t_s": time.perf_counter() - t0})
            if progress:
                bar.set_postfix(loss=f"{history[-1]:.3e}")
    if rebuild is not None:
        renderer, rebuilds = rebuild(), rebuilds + 1
    return {"loss": history, "params": _params(mat), "trace": trace, "rebuilds": rebuilds, "renderer": renderer}


def _side_by_side(path: Path, rows: list[list[Tensor]], scale: int = 4) -> None:
    """One row per view (target, initial, fitted), one exposure per row from the target, upscaled ``scale``x."""
    tiles = []
    for row in rows:
        t = row[0][0]
        mask = (t.sum(0) > 0)
        from torchsss.io import auto_exposure

        e = auto_exposure(t, mask)
        imgs = [tonemap(x[0], e) for x in row]
        sep = torch.ones(3, t.shape[1], 2)
        line = []
        for i, img in enumerate(imgs):
            line += [img] if i == 0 else [sep, img]
        tiles.append(torch.cat(line, dim=2))
    grid = torch.cat([torch.cat([x, torch.ones(3, 2, x.shape[2])], 1) for x in tiles], 1)[:, :-2]
    grid = grid.repeat_interleave(scale, 1).repeat_interleave(scale, 2)
    write_png(path, grid)


def _loss_png(path: Path, loss: list[float], title: str) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # the "plots" extra
        print("matplotlib is not installed (pip install -e '.[plots]'): no loss curve", file=sys.stderr)
        return
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    ax.semilogy(range(len(loss)), loss)
    ax.set_xlabel("iteration (Adam step or LM iteration)")
    ax.set_ylabel("relative squared error (mean over views)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _material_arg(value: str) -> Material:
    value = value.strip()
    return Material.from_json(json.loads(value) if value.startswith("{") else value)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("scene", nargs="?", default="default", help="scene file or 'default' (the shipped spot)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--target-material", type=_material_arg,
                   help="preset name or JSON {sigma_a, sigma_s_prime, eta}: render the targets with the reference")
    g.add_argument("--targets", nargs="+", type=Path, help="target EXR files, one per orbit view")
    p.add_argument("--init-material", type=_material_arg, default=None,
                   help="initial guess (default: sigma_a 0.05, sigma_s' 1.0 mm^-1 in every channel, the scene's eta)")
    p.add_argument("--views", type=int, default=4, help="orbit views (with --target-material)")
    p.add_argument("--size", type=int, default=48, help="image width and height in pixels (with --target-material)")
    p.add_argument("--method", default="splat", choices=DIFFERENTIABLE, help="differentiable method of the fit")
    p.add_argument("--tolerance", type=float, default=None,
                   help="let the planner pick the splat budget for this tolerance (default: --eps)")
    p.add_argument("--eps", type=float, default=0.01, help="splat budget tolerance when no --tolerance is given")
    p.add_argument("--oversample", type=float, default=1.0, help="splat light-view oversampling (no --tolerance)")
    p.add_argument("--splat-method", default="window", choices=("auto", "window", "tile"),
                   help="splat_radiosity's form (window: 2-3x faster than tile under autograd here)")
    p.add_argument("--optimizer", default="lm", choices=("lm", "adam"),
                   help="lm: Levenberg-Marquardt with the reference correction (fit_lm.py; default); adam: Adam")
    p.add_argument("--no-correct", action="store_true",
                   help="lm without the reference's defect correction: fit the fast method's images as they are")
    p.add_argument("--outer", type=int, default=8, help="lm: outer iterations (rebuild + correction) at most")
    p.add_argument("--inner", type=int, default=8, help="lm: LM iterations per outer iteration at most")
    p.add_argument("--steps", type=int, default=60, help="adam: steps")
    p.add_argument("--lr", type=float, default=0.1, help="adam: learning rate (log space)")
    p.add_argument("--fit-eta", action="store_true", help="optimise eta too")
    p.add_argument("--rebuild-every", type=int, default=10,
                   help="adam: rebuild the renderer (its knobs planned from the material) every N steps")
    p.add_argument("--float64", action="store_true", help="render in double precision")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--json", type=Path, default=None, help="write the result here")
    p.add_argument("--out", type=Path, default=None, help="folder of the PNGs (default: beside --json, or out/fit)")
    p.add_argument("--save-targets", action="store_true", help="also write the rendered targets as EXR")
    p.add_argument("--sensitivity", action="store_true",
                   help="also measure what the images can tell apart (see sensitivity(); 6 x views reference renders)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    for name in ("views", "size", "steps", "outer", "inner"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')}: expected a positive int, got {getattr(args, name)}")
    return args


def fit_method_knobs(scene: Scene, mesh, method: str, tolerance: float | None, frames: int, eps: float = 0.01,
                     oversample: float = 1.0, splat_method: str = "window") -> tuple[dict, dict]:
    """Knobs of the fit's renderer: the planner's splat budget (``frames`` = steps x views), the defaults otherwise."""
    if method != "splat":
        return {}, {"method": f"{method} at its default knobs (named on the command line)"}
    if tolerance is None:
        knobs = {"eps": eps, "oversample": oversample, "splat_method": splat_method}
        return knobs, {"method": f"splat {knobs} (--eps, --oversample; --tolerance asks the planner instead)"}
    from torchsss.plan import plan

    p = plan(scene, tolerance=tolerance, frames=frames, methods=["splat"], mesh=mesh)
    if p.method != "splat":  # no splat configuration predicted to meet the tolerance
        return {}, {"method": f"splat at its default knobs: the planner found no splat configuration within "
                              f"{tolerance}"}
    why = f"splat {p.knobs} planned for {tolerance} (predicted error {p.predicted_error:.3g}, frame " \
          f"{p.predicted_frame_s:.3g} s)"
    return {**p.knobs, "splat_method": splat_method}, {"method": why}


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    dtype = torch.float64 if args.float64 else torch.float32
    t_start = time.perf_counter()
    if args.targets:
        images = [read_exr(f) for f in args.targets]
        shapes = {tuple(x.shape) for x in images}
        if len(shapes) != 1 or next(iter(shapes))[0] != 3:
            raise ValueError(f"--targets: expected RGB EXR files of one resolution, got shapes {sorted(shapes)}")
        _, h, w = images[0].shape
        scene = load_fit_scene(args.scene)
        scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=w, height=h))
        mesh = scene.load_mesh(dtype)
        cameras = orbit_cameras(scene.camera, len(images))
        targets = [x.unsqueeze(0).to(dtype) for x in images]
        target_material = None
    else:
        scene = load_fit_scene(args.scene, args.size)
        mesh = scene.load_mesh(dtype)
        cameras = orbit_cameras(scene.camera, args.views)
        target_material = args.target_material
        print(f"rendering {len(cameras)} target views ({args.size}x{args.size}) with the reference (spacing "
              f"{target_spacing(mesh, target_material):.3g} mm) ...")
        targets = render_targets(scene, mesh, target_material, cameras, dtype=dtype,
                                 spacing_mm=target_spacing(mesh, target_material))
    t_targets = time.perf_counter() - t_start
    eta0 = scene.material.eta if scene.material is not None else 1.3
    init = args.init_material or Material.from_json({"sigma_a": [0.05] * 3, "sigma_s_prime": [1.0] * 3, "eta": eta0})
    if target_material is not None and not args.fit_eta:
        init = Material.from_json({"sigma_a": list(init.sigma_a), "sigma_s_prime": list(init.sigma_s_prime),
                                   "eta": target_material.eta})
    fit_scene = dataclasses.replace(scene, material=init)
    knobs, reasons = fit_method_knobs(fit_scene, mesh, args.method, args.tolerance, args.steps * len(cameras),
                                     args.eps, args.oversample, args.splat_method)
    t0 = time.perf_counter()
    material = LogDipoleMaterial.from_material(init, dtype=dtype)
    renderer = build(args.method, mesh, material, dtype=dtype, differentiable=True, **knobs)
    t_setup = time.perf_counter() - t0
    lights = list(scene.lights)
    with torch.no_grad():
        initial_images = [renderer.render(lights, c).radiance for c in cameras]
    initial = _params(material)
    correct = args.optimizer == "lm" and not args.no_correct
    how = (f"{args.steps} Adam steps" if args.optimizer == "adam" else
           f"Levenberg-Marquardt{' with the reference correction' if correct else ''}")
    print(f"fit through {args.method} {renderer.knobs if args.method == 'splat' else ''}".rstrip() +
          f": {len(cameras)} views, {how} (setup {t_setup:.1f} s)")
    t0, c0 = time.perf_counter(), time.process_time()
    knobs_free = {k: v for k, v in knobs.items() if k != "grid"}
    make = lambda: build(args.method, mesh, material, dtype=dtype, differentiable=True, **knobs_free)  # noqa: E731
    if args.optimizer == "adam":
        result = fit(renderer, lights, cameras, targets, steps=args.steps, lr=args.lr, fit_eta=args.fit_eta,
                     progress=not args.no_progress, rebuild_every=args.rebuild_every, rebuild=make)
    else:
        if str(Path(__file__).resolve().parent) not in sys.path:
            sys.path.insert(0, str(Path(__file__).resolve().parent))
        from fit_lm import fit_lm

        material.raw_eta.requires_grad_(args.fit_eta)
        groups = [material.log_sigma_tr, material.log_albedo_ratio] + ([material.raw_eta] if args.fit_eta else [])
        reference_now = lambda: render_targets(scene, mesh, Material.from_json(_params(material)),  # noqa: E731
                                               cameras, dtype=dtype)
        result = fit_lm(make, lights, cameras, targets, groups, [True, True] + [False] * args.fit_eta,
                        correct=reference_now if correct else None, record=lambda: _params(material),
                        outer=args.outer, inner=args.inner, progress=not args.no_progress)
        result["params"] = _params(material)
        result["rebuilds"] = len(result["outer"])
    renderer = result.pop("renderer")
    t_fit, cpu_fit = time.perf_counter() - t0, time.process_time() - c0
    with torch.no_grad():
        fitted_images = reference_now() if correct else [renderer.render(lights, c).radiance for c in cameras]
        final_loss = float(sum(view_loss(a, b) for a, b in zip(fitted_images, targets)) / len(cameras))
    iterations = len(result["trace"])
    out = {"scene": str(args.scene), "method": args.method, "knobs": renderer.knobs, "reasons": reasons,
           "views": len(cameras), "size": [cameras[0].width, cameras[0].height], "optimizer": args.optimizer,
           "corrected": correct, "fitted_render": "reference" if correct else args.method, "steps": iterations,
           "lr": args.lr if args.optimizer == "adam" else None, "fit_eta": args.fit_eta,
           "rebuilds": result["rebuilds"], "dtype": str(dtype).replace("torch.", ""),
           "threads": torch.get_num_threads(), "parameterisation": "log sigma_tr, log(sigma_s'/sigma_a), log eta",
           "initial": initial, "fitted": result["params"],
           "loss": result["loss"] + [final_loss], "trace": result["trace"],
           "time_s": {"targets": t_targets, "setup": t_setup, "fit": t_fit, "fit_cpu": cpu_fit,
                      "per_step": t_fit / max(iterations, 1), "total": time.perf_counter() - t_start}}
    if args.optimizer == "lm":
        out["outer"], out["renders"] = result["outer"], result["renders"]
    if target_material is not None:
        out["target"] = {"name": target_material.name, "sigma_a": list(target_material.sigma_a),
                         "sigma_s_prime": list(target_material.sigma_s_prime), "eta": target_material.eta}
        out["relative_error"] = relative_errors(result["params"], target_material)
        out["max_relative_error"] = {k: max(v) if isinstance(v, list) else v for k, v in out["relative_error"].items()}
        if args.sensitivity:
            out["sensitivity"] = sensitivity(scene, mesh, target_material, cameras, targets, args.method,
                                             knobs_free, dtype)
    out_dir = args.out or (args.json.parent if args.json else Path("out/fit"))
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = args.json.stem if args.json else "fit"
    _loss_png(out_dir / f"{stem}_loss.png", out["loss"],
              f"{scene.mesh}: fit of {target_material.name if target_material else 'EXR targets'} through "
              f"{args.method} ({args.optimizer}), {len(cameras)} views")
    _side_by_side(out_dir / f"{stem}_side_by_side.png",
                  [[t, i, f] for t, i, f in zip(targets, initial_images, fitted_images)])
    if args.save_targets and target_material is not None:
        for k, t in enumerate(targets):
            write_exr(out_dir / f"{stem}_target{k}.exr", t[0])
    out["files"] = [str(out_dir / f"{stem}_loss.png"), str(out_dir / f"{stem}_side_by_side.png")]
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1))
    _report(out)
    return out


def _report(out: dict) -> None:
    fmt = lambda xs: "[" + ", ".join(f"{x:.4g}" for x in xs) + "]"  # noqa: E731
    print(f"loss {out['loss'][0]:.3e} -> {out['loss'][-1]:.3e} ({out['fitted_render']} at the fitted material) in "
          f"{out['time_s']['fit']:.1f} s ({out['steps']} iterations, {out['time_s']['per_step']:.2f} s each; "
          f"{out['time_s']['fit_cpu']:.1f} s of CPU time on "
          f"{out['threads']} threads)")
    for key in ("sigma_a", "sigma_s_prime"):
        line = f"{key:14s} fitted {fmt(out['fitted'][key])}"
        if "target" in out:
            line += f"  target {fmt(out['target'][key])}  rel. error {fmt(out['relative_error'][key])}"
        print(line)
    if "sensitivity" in out:
        sen = out["sensitivity"]
        print(f"image change per +10%: sigma_a {fmt(sen['sigma_a'])}, sigma_s' {fmt(sen['sigma_s_prime'])}; "
              f"{out['method']}'s own error {fmt(sen['method_error'])} (per channel)")
    print(f"{'eta':14s} fitted {out['fitted']['eta']:.4g}" + (f"  target {out['target']['eta']:.4g}"
                                                               if "target" in out else ""))


if __name__ == "__main__":
    main()
