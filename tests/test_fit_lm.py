"""examples/fit_lm.py (issue 18): Levenberg-Marquardt with the reference's defect correction.

The per-group Jacobian columns against one parameter at a time, the autograd gradient against the
central-difference one, the correction's fixed point on a model with a known bias (closed form), and a fit of
potato through splat on a small scene that recovers every coefficient.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import fit_lm
import fit_material

sys.path.pop(0)

from torchsss.geometry import Camera, PointLight, sphere
from torchsss.physics.materials import Material
from torchsss.pipelines import build


def _small_splat(dtype=torch.float64):
    mesh = sphere(8.0, 2, dtype=dtype)
    cams = fit_material.orbit_cameras(Camera(eye=(0.0, 10.0, 50.0), target=(0.0, 0.0, 0.0), fov_deg=25, width=12,
                                             height=12), 2)
    lights = [PointLight((40.0, 20.0, 30.0), 3e3)]
    mat = fit_material.LogDipoleMaterial.from_material(Material.from_json("skin1"), dtype=dtype)
    mat.raw_eta.requires_grad_(False)
    renderer = build("splat", mesh, mat, dtype=dtype, differentiable=True, eps=0.01)
    return mesh, cams, lights, mat, renderer


def _residual(renderer, lights, cams, targets):
    return torch.stack([((renderer.render(lights, c).radiance - t) / t.norm()).reshape(3, -1)
                        for c, t in zip(cams, targets)])


def test_group_columns_equal_one_parameter_at_a_time():
    """Channel c's pixels depend on channel c's coefficients only: a group moved in every channel gives C columns."""
    _mesh, cams, lights, mat, renderer = _small_splat()
    with torch.no_grad():
        targets = [renderer.render(lights, c).radiance * 1.1 for c in cams]
        res = lambda: _residual(renderer, lights, cams, targets)  # noqa: E731
        groups = [mat.log_sigma_tr, mat.log_albedo_ratio]
        jac = fit_lm.fd_jacobian(res, groups, [True, True], step=1e-4)
        assert jac.shape == (2 * 3 * 144, 6)
        p0 = [g.clone() for g in groups]
        for j in range(6):  # the same column from moving one entry
            g, c = groups[j // 3], j % 3
            g.data[c] += 1e-4
            plus = res()
            g.data[c] -= 2e-4
            minus = res()
            g.data[c] = p0[j // 3][c]
            single = ((plus - minus) / 2e-4).reshape(-1)
            assert float(single.abs().max()) > 1e-3  # the coefficient moves its channel
            torch.testing.assert_close(jac[:, j], single, rtol=1e-6, atol=1e-9)
        # eta moves every channel: one full column
        et = fit_lm.fd_jacobian(res, [mat.raw_eta], [False], step=1e-4)
        assert et.shape == (2 * 3 * 144, 1) and bool((et.reshape(2, 3, -1).abs().amax(dim=(0, 2)) > 1e-3).all())


def test_group_columns_validate():
    with pytest.raises(ValueError, match="per-channel group"):
        fit_lm.fd_jacobian(lambda: torch.zeros(1, 3, 4), [torch.zeros(2)], [True])


def test_autograd_gradient_is_twice_jacobian_transpose_residual():
    """The LM step's right-hand side (autograd through splat) against the central-difference Jacobian."""
    _mesh, cams, lights, mat, renderer = _small_splat()
    with torch.no_grad():
        targets = [renderer.render(lights, c).radiance for c in cams]
    with torch.no_grad():  # move away from the optimum
        mat.log_sigma_tr += torch.tensor([0.2, -0.1, 0.05], dtype=torch.float64)
        mat.log_albedo_ratio += torch.tensor([-0.3, 0.1, 0.2], dtype=torch.float64)
    r = _residual(renderer, lights, cams, targets)
    (r**2).sum().backward()
    grad = torch.cat([mat.log_sigma_tr.grad, mat.log_albedo_ratio.grad])
    with torch.no_grad():
        jac = fit_lm.fd_jacobian(lambda: _residual(renderer, lights, cams, targets),
                                 [mat.log_sigma_tr, mat.log_albedo_ratio], [True, True], step=1e-5)
        fd = 2.0 * jac.T @ r.detach().reshape(-1)
    torch.testing.assert_close(grad, fd, rtol=1e-5, atol=1e-9)


class _Toy:
    """Per channel c, pixel x in [0, 3]: the reference is :math:`a_c e^{-s_c x}` (a = sigmoid(albedo), s = exp)."""

    def __init__(self, log_s, logit_a, bias: float) -> None:
        self.log_s, self.logit_a, self.bias = log_s, logit_a, bias
        self.x = torch.linspace(0.0, 3.0, 40, dtype=torch.float64).reshape(1, 1, 1, 40)

    def render(self, lights, camera):
        a = torch.sigmoid(self.logit_a).reshape(1, -1, 1, 1)
        s = torch.exp(self.log_s).reshape(1, -1, 1, 1)
        img = a * torch.exp(-s * self.x)
        # the fast model's error: 10-40% too bright, growing across the image (no parameter change absorbs it)
        return SimpleNamespace(radiance=img * (1.0 + self.bias * (1.0 + self.x)))


def test_defect_correction_converges_to_the_reference_fit():
    """Through a model 10-40% off, the corrected fit recovers the reference's parameters; uncorrected it is biased."""
    truth_s, truth_a = torch.tensor([-0.5, 0.3, 1.0], dtype=torch.float64), torch.tensor([1.0, 0.0, -1.0],
                                                                                         dtype=torch.float64)
    targets = [_Toy(truth_s, truth_a, 0.0).render(None, None).radiance]
    results = {}
    for correct in (False, True):
        log_s = torch.zeros(3, dtype=torch.float64, requires_grad=True)
        logit_a = torch.zeros(3, dtype=torch.float64, requires_grad=True)
        ref = lambda: [_Toy(log_s.detach(), logit_a.detach(), 0.0).render(None, None).radiance]  # noqa: E731,B023
        out = fit_lm.fit_lm(lambda: _Toy(log_s, logit_a, 0.1), [], [None], targets,  # noqa: B023
                            [log_s, logit_a], [True, True], correct=ref if correct else None, outer=12, inner=10,
                            tol=1e-9, rtol=1e-12, progress=False)
        results[correct] = (log_s.detach().clone(), logit_a.detach().clone(), out)
    s, a, out = results[True]
    torch.testing.assert_close(s, truth_s, rtol=0, atol=1e-6)
    torch.testing.assert_close(a, truth_a, rtol=0, atol=1e-6)
    assert out["reference_loss"] < 1e-12 and out["outer"][-1]["max_change"] < 1e-6
    s0, _a0, out0 = results[False]
    assert float((s0 - truth_s).abs().max()) > 0.05  # without the correction the model's error moves the fit
    assert out0["reference_loss"] is None


def test_fit_lm_validates():
    with pytest.raises(ValueError, match="targets"):
        fit_lm.fit_lm(lambda: None, [], [None, None], [torch.zeros(1, 3, 2, 2)], [], [], progress=False)
    with pytest.raises(ValueError, match="per_channel"):
        fit_lm.fit_lm(lambda: None, [], [None], [torch.zeros(1, 3, 2, 2)], [torch.zeros(3)], [], progress=False)


def test_lm_fit_of_potato_end_to_end(tmp_path):
    """The example's default solver recovers every potato coefficient from 2 small views of a sphere."""
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({
        "mesh": "sphere", "size_mm": 16.0, "material": "skin1",
        "lights": [{"type": "point", "position": [40, 20, 30], "intensity": 3000}],
        "camera": {"eye": [0, 10, 60], "target": [0, 0, 0], "fov_deg": 25, "width": 24, "height": 24}}))
    out = tmp_path / "fit.json"
    res = fit_material.main([str(scene), "--target-material", "potato", "--views", "2", "--size", "24",
                             "--no-progress", "--json", str(out)])
    saved = json.loads(out.read_text())
    assert saved["optimizer"] == "lm" and saved["corrected"] and saved["fitted_render"] == "reference"
    assert saved["fitted"] == res["fitted"] and len(saved["outer"]) >= 2
    err = saved["relative_error"]
    assert max(err["sigma_a"] + err["sigma_s_prime"]) < 0.02, err  # 0.24% measured
    assert saved["loss"][-1] < 1e-3 * saved["loss"][0]
