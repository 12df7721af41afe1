import pytest
import torch

import torchsss
from torchsss import DipoleMaterial
from torchsss.modules import POSITIVE_FLOOR
from torchsss.physics import dipole_rd, preset, preset_names, total_diffuse_reflectance
from torchsss.testing import assert_close


def test_presets_embedded_and_match_shared_csv(shared_dir):
    import csv

    rows = [r for r in (shared_dir / "data" / "materials_jensen2001.csv").read_text().splitlines()
            if r and not r.startswith("#")]
    table = {row["name"]: row for row in csv.DictReader(rows)}
    assert sorted(table) == sorted(preset_names()) and len(table) == 12
    for name, row in table.items():
        p = preset(name)
        assert p.sigma_a == tuple(float(row[f"sigma_a_{c}"]) for c in "rgb")
        assert p.sigma_s_prime == tuple(float(row[f"sigma_s_prime_{c}"]) for c in "rgb")
        assert p.eta == float(row["eta"])


@pytest.mark.parametrize("name", ["marble", "MARBLE", " Skin1 ", "spectralon"])
def test_from_preset_case_insensitive(name):
    m = DipoleMaterial.from_preset(name, dtype=torch.float64)
    p = preset(name)
    assert_close(m.sigma_s_prime, torch.tensor(p.sigma_s_prime, dtype=torch.float64), rtol=1e-12, atol=0)
    assert_close(m.sigma_a, torch.tensor(p.sigma_a, dtype=torch.float64).clamp_min(POSITIVE_FLOOR), rtol=1e-9,
                 atol=0)
    assert m.eta.item() == pytest.approx(1.3, rel=1e-12)


def test_unknown_preset_lists_valid_names():
    with pytest.raises(ValueError, match="marble") as info:
        DipoleMaterial.from_preset("jade")
    assert "jade" in str(info.value) and "skin1" in str(info.value)
    with pytest.raises(TypeError, match="name"):
        DipoleMaterial.from_preset(3)


def test_forward_matches_functional(dtype):
    m = DipoleMaterial([0.01, 0.02, 0.03], [1.0, 1.5, 2.0], 1.3, dtype=dtype)
    r = torch.linspace(0, 10, 21, dtype=dtype).unsqueeze(-1)
    assert_close(m(r), dipole_rd(r, m.sigma_a, m.sigma_s_prime, m.eta))
    assert m(r).dtype == dtype
    assert_close(m.total_diffuse_reflectance(), total_diffuse_reflectance(m.sigma_a, m.sigma_s_prime, m.eta))


def test_from_scattering():
    m = DipoleMaterial.from_scattering([0.01], [10.0], 0.9, dtype=torch.float64)
    assert m.sigma_s_prime.item() == pytest.approx(1.0, rel=1e-12)
    with pytest.raises(ValueError, match="g"):
        DipoleMaterial.from_scattering([0.01], [10.0], 1.0)
    with pytest.raises(ValueError, match="sigma_s"):
        DipoleMaterial.from_scattering([0.01], [-1.0], 0.5)


def test_gradients_reach_parameters_and_stay_in_range():
    m = DipoleMaterial.from_preset("skin1", dtype=torch.float64)
    target = DipoleMaterial.from_preset("marble", dtype=torch.float64)
    r = torch.linspace(0, 8, 64, dtype=torch.float64).unsqueeze(-1)
    opt = torch.optim.Adam(m.parameters(), lr=0.2)
    first = None
    for _ in range(60):
        opt.zero_grad()
        loss = ((m(r) - target(r).detach()) ** 2).mean() / (target(r).detach() ** 2).mean()
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in m.parameters())
        opt.step()
        first = loss.item() if first is None else first
        assert torch.all(m.sigma_a > 0) and torch.all(m.sigma_s_prime > 0) and torch.all(m.eta > 0)
    assert loss.item() < 0.1 * first


def test_gradcheck_material_module():
    m = DipoleMaterial([0.01, 0.2], [1.0, 0.5], 1.3, dtype=torch.float64)
    r = torch.tensor([[0.0], [0.5], [3.0]], dtype=torch.float64)

    def f(raw_a, raw_s, raw_e):
        return torch.func.functional_call(m, {"raw_sigma_a": raw_a, "raw_sigma_s_prime": raw_s, "raw_eta": raw_e},
                                          (r,))

    params = tuple(p.detach().clone().requires_grad_(True) for p in (m.raw_sigma_a, m.raw_sigma_s_prime, m.raw_eta))
    assert torch.autograd.gradcheck(f, params)


def test_zero_absorption_gets_floor_and_finite_gradient():
    m = DipoleMaterial.from_preset("spectralon", dtype=torch.float64)
    assert torch.all(m.sigma_a <= 1.0001 * POSITIVE_FLOOR)
    m(torch.tensor([[0.0], [1.0]], dtype=torch.float64)).sum().backward()
    assert torch.isfinite(m.raw_sigma_a.grad).all()
    # the floor is invisible in the result
    exact = dipole_rd(torch.tensor([[1.0]], dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                      m.sigma_s_prime.detach(), 1.3)
    assert_close(m(torch.tensor([[1.0]], dtype=torch.float64)).detach(), exact, rtol=1e-9, atol=0)


def test_state_dict_round_trip_and_device(device):
    m = DipoleMaterial.from_preset("ketchup").to(device)
    m2 = DipoleMaterial([1.0, 1.0, 1.0], [1.0, 1.0, 1.0]).to(device)
    m2.load_state_dict(m.state_dict())
    r = torch.rand(7, 1, device=device)
    assert torch.equal(m(r), m2(r))
    assert m(r).device.type == device.type


@pytest.mark.parametrize(
    "args,exc,match",
    [
        (([-0.1, 0.1, 0.1], [1.0, 1.0, 1.0]), ValueError, "sigma_a"),
        (([0.1, float("nan"), 0.1], [1.0, 1.0, 1.0]), ValueError, "sigma_a"),
        (([0.1, 0.1, 0.1], [1.0, -1.0, 1.0]), ValueError, "sigma_s_prime"),
        (([0.1, 0.1, 0.1], [1.0, 1.0]), ValueError, "sigma_s_prime"),
        (([0.1, 0.1, 0.1], [1.0, 1.0, 1.0], 0.0), ValueError, "eta"),
        (([0.1, 0.1, 0.1], [1.0, 1.0, 1.0], [1.3, 1.3]), ValueError, "eta"),
        (([0.0], [0.0]), ValueError, "sigma_a \\+ sigma_s_prime"),
        (("abc", [1.0]), TypeError, "sigma_a"),
    ],
)
def test_constructor_errors(args, exc, match):
    with pytest.raises(exc, match=match):
        DipoleMaterial(*args)


def test_public_api():
    assert torchsss.DipoleMaterial is DipoleMaterial
    assert hasattr(torchsss.DipoleMaterial, "from_preset")
    assert "DipoleMaterial" in repr(DipoleMaterial.from_preset("marble"))
