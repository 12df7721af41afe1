"""Data-parallel material fitting: the views of ``fit_material.py`` sharded over processes with DDP (issue 18).

Launch::

    torchrun --standalone --nproc_per_node 2 examples/fit_material_ddp.py [SCENE] --target-material potato \\
        --views 4 --steps 20 --json out/fit/ddp.json
    python examples/fit_material_ddp.py [SCENE] --target-material potato --views 4 --steps 20 --json single.json

Rank r of W renders views r, r + W, r + 2W, ... of the orbit (targets and fit); every rank holds the same
:class:`~fit_material.LogDipoleMaterial` and renderer (built identically from the same scene, so no state differs
between ranks; every rank rebuilds its renderer at the same steps, from the same parameters).
The material is wrapped in a small ``nn.Module`` (:class:`ShardLoss`) whose ``forward`` renders the
rank's views and returns :math:`\\frac{W}{V}\\sum_{v \\in \\text{rank}} \\ell_v`, and that module is wrapped in
:class:`torch.nn.parallel.DistributedDataParallel`: DDP averages the gradients over the W ranks, which gives
:math:`\\frac{1}{V}\\sum_v \\nabla\\ell_v`, the single-process gradient of the mean loss over all V views. Adam then
takes the same step on every rank. The backend is gloo on the CPU and nccl with ``--device cuda`` (one GPU per
rank, ``LOCAL_RANK``). Without ``torchrun`` (no ``WORLD_SIZE`` in the environment) the script runs the same fit in
one process, for comparison: the parameters agree to float rounding (the per-rank partial sums are added in
another order), 1e-5 or better after the same steps (``tests/test_ddp_fit.py``).

Rank 0 writes ``--json``: the fitted parameters, the loss history (the global loss, all-reduced), the world size and
the times.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor, nn

import torchsss
from torchsss.pipelines import build

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit_material import (
    LogDipoleMaterial,
    _material_arg,
    _params,
    fit,
    fit_method_knobs,
    load_fit_scene,
    orbit_cameras,
    relative_errors,
    render_targets,
    view_loss,
)

__all__ = ["ShardLoss", "main"]


class ShardLoss(nn.Module):
    """This rank's share of the loss: :math:`\\frac{W}{V}\\sum_{v} \\ell_v` over the rank's views.

    It holds the material (a registered submodule, the parameters DDP synchronises) and a renderer that renders
    with that very module; ``forward()`` renders the rank's views. A rank with no view returns
    :math:`0 \\cdot \\sum p` so that every parameter still takes part in the reduction.
    """

    def __init__(self, material: nn.Module, lights, cameras, targets, world: int, views: int) -> None:
        super().__init__()
        self.material = material
        self._lights, self._cameras, self._targets = lights, cameras, targets
        self.scale = world / views

    def forward(self, renderer) -> Tensor:
        """The rank's share of the loss through ``renderer`` (built on :attr:`material`), a :math:`()` tensor."""
        if renderer.material is not self.material:
            raise ValueError("renderer: expected a renderer of this module's material, got another material")
        loss = sum(p.sum() for p in self.material.parameters() if p.requires_grad) * 0.0
        for cam, t in zip(self._cameras, self._targets):
            loss = loss + view_loss(renderer.render(self._lights, cam).radiance, t)
        return loss * self.scale


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene", nargs="?", default="default")
    p.add_argument("--target-material", type=_material_arg, required=True)
    p.add_argument("--init-material", type=_material_arg, default=None)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--size", type=int, default=48)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--lr", type=float, default=0.1)
    p.add_argument("--eps", type=float, default=0.01)
    p.add_argument("--oversample", type=float, default=1.0)
    p.add_argument("--fit-eta", action="store_true")
    p.add_argument("--rebuild-every", type=int, default=10)
    p.add_argument("--float64", action="store_true")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, default=None, help="torch threads per process")
    p.add_argument("--json", type=Path, default=None)
    return p.parse_args(argv)


def main(argv=None) -> dict | None:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    distributed = "WORLD_SIZE" in os.environ
    if distributed:
        backend = "nccl" if args.device == "cuda" else "gloo"
        dist.init_process_group(backend)
        rank, world = dist.get_rank(), dist.get_world_size()
    else:
        rank, world = 0, 1
    device = torch.device("cpu")
    if args.device == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
        torch.cuda.set_device(device)
    dtype = torch.float64 if args.float64 else torch.float32
    t_start = time.perf_counter()
    scene = load_fit_scene(args.scene, args.size)
    mesh = scene.load_mesh(dtype)
    if device.type != "cpu":
        mesh = mesh.with_device(device)
    cameras = orbit_cameras(scene.camera, args.views)[rank::world]  # this rank's shard of the views
    target = args.target_material
    targets = render_targets(scene, mesh, target, cameras, dtype=dtype) if cameras else []
    init = args.init_material or target.__class__.from_json(
        {"sigma_a": [0.05] * 3, "sigma_s_prime": [1.0] * 3, "eta": target.eta})
    knobs, _ = fit_method_knobs(scene, mesh, "splat", None, 1, args.eps, args.oversample, "window")
    material = LogDipoleMaterial.from_material(init, dtype=dtype, device=device)
    renderer = build("splat", mesh, material, dtype=dtype, differentiable=True, **knobs)
    material.raw_eta.requires_grad_(args.fit_eta)  # before DDP: it registers the parameters that need gradients
    shard = ShardLoss(material, list(scene.lights), cameras, targets, world, args.views)
    model = nn.parallel.DistributedDataParallel(shard) if distributed else shard

    def loss_of_views(renderer, _lights, _cameras, _targets) -> Tensor:
        loss = model(renderer)
        loss.backward()  # DDP all-reduces (averages) the gradients here
        total = loss.detach().clone()
        if distributed:
            dist.all_reduce(total)
            total /= world
        return total

    t0 = time.perf_counter()
    with torchsss.validation(False):
        result = fit(renderer, list(scene.lights), cameras, targets, steps=args.steps, lr=args.lr,
                     fit_eta=args.fit_eta, progress=False, loss_of_views=loss_of_views,
                     rebuild=lambda: build("splat", mesh, material, dtype=dtype, differentiable=True, **knobs),
                     rebuild_every=args.rebuild_every)
        renderer = result.pop("renderer")
    t_fit = time.perf_counter() - t0
    out = None
    if rank == 0:
        out = {"world_size": world, "backend": (dist.get_backend() if distributed else None), "views": args.views,
               "size": args.size, "steps": args.steps, "dtype": str(dtype).replace("torch.", ""),
               "knobs": renderer.knobs, "fitted": result["params"], "loss": result["loss"],
               "raw": {n: p.detach().cpu().tolist() for n, p in material.named_parameters()},
               "relative_error": relative_errors(result["params"], target),
               "time_s": {"fit": t_fit, "per_step": t_fit / args.steps, "total": time.perf_counter() - t_start}}
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(out, indent=1))
        print(f"world {world}: loss {out['loss'][0]:.4e} -> {out['loss'][-1]:.4e}, fitted {_params(material)}, "
              f"{t_fit:.1f} s")
    if distributed:
        dist.destroy_process_group()
    return out


if __name__ == "__main__":
    main()
