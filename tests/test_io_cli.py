import json
import subprocess
import sys
import zlib

import pytest
import torch

from torchsss.cli import main
from torchsss.io import read_exr, tonemap, write_exr, write_png
from torchsss.physics import dipole_rd, preset


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_exr_round_trip(tmp_path, channels):
    img = torch.rand(channels, 5, 7) * 100
    p = write_exr(tmp_path / "sub" / "a.exr", img)
    back = read_exr(p)
    assert back.dtype == torch.float32 and torch.equal(back, img)


def test_exr_bad_input(tmp_path):
    with pytest.raises(ValueError, match="image"):
        write_exr(tmp_path / "a.exr", torch.rand(2, 4, 4))
    with pytest.raises(TypeError, match="image"):
        write_exr(tmp_path / "a.exr", [[1.0]])
    with pytest.raises(FileNotFoundError, match="path"):
        read_exr(tmp_path / "missing.exr")


def test_png_is_valid(tmp_path):
    img = torch.linspace(0, 1, 3 * 4 * 6).reshape(3, 4, 6)
    data = write_png(tmp_path / "a.png", img).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    # decode the single IDAT and check the pixel bytes
    idat_len = int.from_bytes(data[33:37], "big")
    assert data[37:41] == b"IDAT"
    raw = zlib.decompress(data[41:41 + idat_len])
    assert len(raw) == 4 * (1 + 6 * 3)
    assert raw[1] == 0 and raw[-1] == 255  # first pixel black, last white
    t = tonemap(torch.rand(3, 8, 8))
    assert t.min() >= 0 and t.max() <= 1


def test_profiles_command_writes_outputs(tmp_path, capsys):
    assert main(["profiles", "--out", str(tmp_path), "--no-plot"]) == 0
    summary = json.loads((tmp_path / "profiles.json").read_text())
    assert len(summary["presets"]) == 12
    for rec in summary["presets"].values():
        assert max(rec["integral_rel_error"]) < 1e-6
    img = read_exr(tmp_path / "profiles.exr")
    assert img.shape == (3, 12 * 16, 512)
    # band 5 is marble (table order); column 0 is r = 0
    p = preset("marble")
    expected = dipole_rd(torch.zeros(1, 1, dtype=torch.float64), torch.tensor(p.sigma_a, dtype=torch.float64),
                         torch.tensor(p.sigma_s_prime, dtype=torch.float64), 1.3)[0]
    assert torch.allclose(img[:, 5 * 16, 0].double(), expected, rtol=1e-6)
    assert (tmp_path / "profiles.png").read_bytes()[:4] == b"\x89PNG"
    assert "max relative error" in capsys.readouterr().out


def test_module_entry_point_errors(capsys):
    res = subprocess.run([sys.executable, "-m", "torchsss", "profiles", "--eps", "2"], capture_output=True,
                         text=True)
    assert res.returncode != 0 and "--eps" in res.stderr
    # the same entry point's argument parser, in process (no second interpreter start-up)
    with pytest.raises(SystemExit) as err:
        main(["nonsense"])
    assert err.value.code != 0 and "invalid choice" in capsys.readouterr().err


def test_checks_helpers():
    from torchsss._checks import check_shape

    assert check_shape(torch.zeros(2, 5, 3), "x", "B,N,3") == {"B": 2, "N": 5}
    with pytest.raises(ValueError, match=r"x: expected shape \(B, N, 3\)"):
        check_shape(torch.zeros(2, 5, 4), "x", "B,N,3")
    with pytest.raises(ValueError, match="B=3"):
        check_shape(torch.zeros(2, 5, 3), "x", "B,N,3", B=3)


def test_assert_close_reports_location():
    from torchsss.testing import assert_close

    a = torch.zeros(3, 4)
    b = a.clone()
    b[2, 1] = 1.0
    with pytest.raises(AssertionError, match=r"max abs diff 1\.000e\+00 at \(2, 1\)"):
        assert_close(a, b)
    assert_close(torch.tensor([1.0, float("nan")]), torch.tensor([1.0, float("nan")]))
    with pytest.raises(AssertionError, match="NaN"):
        assert_close(torch.tensor([1.0, float("nan")]), torch.tensor([1.0, 2.0]))
    with pytest.raises(AssertionError, match="shape"):
        assert_close(torch.zeros(2), torch.zeros(3))
    # per-dtype defaults: float16 is looser than float32
    assert_close(torch.tensor([1.0], dtype=torch.float16), torch.tensor([1.001], dtype=torch.float16))
    with pytest.raises(AssertionError):
        assert_close(torch.tensor([1.0]), torch.tensor([1.001]))
