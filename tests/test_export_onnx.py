"""ONNX export of the registered modules: dynamo exporter, onnxruntime at a different size than the export size."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxscript")

# torch's own exporter internals warn about a deprecated pytree API; not ours to fix.
pytestmark = [
    pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning"),
    pytest.mark.filterwarnings("ignore:# The axis name:UserWarning"),
]

from torchsss import DipoleMaterial, DipoleProfile  # noqa: E402
from torchsss.export import (  # noqa: E402
    EXPORTABLE,
    MATERIAL_PRESETS,
    DynamicShapeError,
    compare_with_eager,
    export_case,
    export_onnx,
    material_inputs,
    run_onnxruntime,
    verify_dynamic_dims,
)
from torchsss.modules import SplatTranslucency  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "export" / "onnx_export.py"
RTOL = 1e-5
TINY32 = float(np.finfo(np.float32).tiny)


@pytest.fixture
def exported(registry_export):
    """Each registry entry exported once per session (tests/conftest.py): name -> (case, path, export seconds)."""
    return registry_export


def _registry_params():
    return [pytest.param(n, marks=pytest.mark.slow) if EXPORTABLE[n]().slow else n for n in sorted(EXPORTABLE)]


def _declared(case):
    """(input index, axis) of every dynamic dim the case declares."""
    out = []
    for i, spec in enumerate(case.dynamic_shapes):
        out += [(i, d) for d in (spec or {})]
    return out


def test_registry_has_every_per_frame_module():
    assert len(EXPORTABLE) >= 12
    for name in ("irradiance_atlas", "local_response", "global_response", "lensch", "splat", "icdf_sampler", "icdf",
                 "hybrid", "newton", "caustic_map", "profile", "material"):
        assert name in EXPORTABLE
    assert not all(EXPORTABLE[n]().slow for n in EXPORTABLE)  # some run in the default test run


@pytest.mark.parametrize("name", _registry_params())
def test_registry_entry_matches_eager_at_export_and_test_size(name, exported, tmp_path, monkeypatch):
    case, path, seconds = exported(name)
    print(f"{name}: export {seconds:.1f} s")
    # The test size must differ from the export size, or frozen sizes would go unnoticed.
    assert [a.shape for a in case.test_args] != [a.shape for a in case.example_args]

    model = onnx.load(str(path))
    assert {o.version for o in model.opset_import if o.domain in ("", "ai.onnx")} == {18}
    # every declared dynamic dim is symbolic in the file (independently of export_onnx's own check)
    inits = {t.name for t in model.graph.initializer}
    inputs = [v for v in model.graph.input if v.name not in inits]
    declared = _declared(case)
    assert declared
    for i, d in declared:
        assert inputs[i].type.tensor_type.shape.dim[d].dim_param, (name, i, d)

    for args in (case.example_args, case.test_args):
        with torch.no_grad():
            scale = None if case.scale is None else case.scale(*args)
            eager = case.module(*args)
        eager = [eager] if isinstance(eager, torch.Tensor) else list(eager.values() if isinstance(eager, dict)
                                                                       else eager)
        res = compare_with_eager(case.module, path, args, scale=scale)
        assert res["shapes"] == [tuple(e.shape) for e in eager]
        assert res["compared"] > 0
        assert res["zero_pattern_match"] and res["underflow_pattern_match"] and res["nonfinite_match"], res
        if case.atol is not None:
            assert res["max_abs_diff"] <= case.atol, res
            continue
        assert res["max_rel_diff"] <= case.rtol <= 1e-3, res
        # Independent check of the same claims straight from the arrays (first output).
        out = run_onnxruntime(path, args)[0]
        e = eager[0].numpy().astype(np.float64)
        o = out.astype(np.float64)
        normal = np.abs(e) > TINY32
        den = np.abs(e) if scale is None else np.maximum(np.abs(e), scale.numpy().astype(np.float64))
        assert np.max(np.abs(o[normal] - e[normal]) / den[normal]) <= case.rtol
        np.testing.assert_array_equal(e == 0, o == 0)

    # the export script's own check of the entry (``onnx_export.py NAME`` / ``--all``), on this file
    script = _load_script()
    monkeypatch.setattr(script, "export_onnx", lambda module, args, out, **kw: Path(shutil.copy(path, out)))
    assert script.run_entry(name, tmp_path / f"{name}.onnx")["ok"]


# -- dynamic dimensions verified ------------------------------------------------------------------------------------
def _model_with_input_dims(dims):
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("r", TensorProto.FLOAT, dims)
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, dims)
    graph = helper.make_graph([helper.make_node("Identity", ["r"], ["y"])], "g", [x], [y])
    return helper.make_model(graph)


def test_verify_dynamic_dims_names_the_specialised_dimension():
    verify_dynamic_dims(_model_with_input_dims(["N", 1]), [(0, "r", 0, "N")])  # symbolic: fine
    with pytest.raises(DynamicShapeError, match=r"froze N \(input 'r', axis 0\): specialised to 256"):
        verify_dynamic_dims(_model_with_input_dims([256, 1]), [(0, "r", 0, "N")])
    with pytest.raises(DynamicShapeError, match=r"M \(input 'r', axis 2\): the input has rank 2"):
        verify_dynamic_dims(_model_with_input_dims(["N", 1]), [(0, "r", 2, "M")])


class _Pairs(torch.nn.Module):
    """reference_radiosity over (B, N) sources and (B, M) receivers: the sampling composites' core."""

    def __init__(self):
        super().__init__()
        self.material = DipoleMaterial.from_preset("skin1")

    def forward(self, src, e, area, dst):
        from torchsss.ops.reference import reference_radiosity

        return reference_radiosity(src, e, area, dst, self.material)


def _pairs_args(n, m, seed):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(1, n, 3, generator=g) * 10, torch.rand(1, n, 3, generator=g), torch.rand(1, n, generator=g),
            torch.rand(1, m, 3, generator=g) * 10)


def test_export_raises_when_the_chunk_loops_freeze_n_and_m(tmp_path, monkeypatch):
    n, m = torch.export.Dim("N"), torch.export.Dim("M")
    dyn = ({1: n}, {1: n}, {1: n}, {1: m})
    # the exported (unchunked) formulation keeps N and M symbolic and matches eager at other sizes
    path = export_onnx(_Pairs(), _pairs_args(50, 20, 0), tmp_path / "pairs.onnx", dynamic_shapes=dyn)
    res = compare_with_eager(_Pairs(), path, _pairs_args(77, 31, 1))
    assert res["shapes"] == [(1, 31, 3)] and res["max_rel_diff"] <= 1e-5, res
    # the eager chunk loops (min(m, 4096), range(0, n, chunk)) specialise both: the export says so, by name
    import torchsss.ops.reference as ref

    monkeypatch.setattr(ref, "is_exporting", lambda: False)
    with pytest.raises(DynamicShapeError, match=r"N \(input 'src', axis 1\): specialised to 50.*"
                                                 r"M \(input 'dst', axis 1\): specialised to 20"):
        export_onnx(_Pairs(), _pairs_args(50, 20, 0), tmp_path / "frozen.onnx", dynamic_shapes=dyn)


# -- no silent truncation in the splat graph --------------------------------------------------------------------------
def test_splat_graph_reports_truncated_splats(exported):
    from torchsss.export.registry import SPLAT_WINDOW, _splat_inputs
    from torchsss.ops.splat import splat_window_size

    case, path, _ = exported("splat")
    exact = SplatTranslucency(DipoleMaterial.from_preset("skin1"), method="tile")
    reach = float(case.module.splat.r_max)
    for (s, h, w), truncated in (((45, 21, 23), False), ((60, 64, 64), True)):
        args = _splat_inputs(s, h, w, 3)
        img, count = run_onnxruntime(path, args)
        with torch.no_grad():
            ref = exact(*args).numpy()
            eager_count = case.module(*args)[1].numpy()
        need = splat_window_size(args[0], args[4], reach, h, w)
        np.testing.assert_array_equal(count, eager_count)
        if truncated:
            # the window is too small for this image: the graph says how many splats may have lost light, and
            # light was indeed lost against the exact (window-free) tile path
            assert need > SPLAT_WINDOW and count[0] > 0
            assert img.sum() < ref.sum() * (1 - 1e-3)
        else:
            assert need <= SPLAT_WINDOW and count[0] == 0
            np.testing.assert_allclose(img, ref, rtol=1e-4, atol=1e-7 * ref.max())


# -- materials as inputs ----------------------------------------------------------------------------------------------
def _session(path):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


@pytest.mark.parametrize("name", ["splat_materials", "lensch_materials", "icdf_materials"])
def test_material_inputs_render_any_material_in_one_session(name, exported):
    case, path, _ = exported(name)
    sess = _session(path)
    names = [i.name for i in sess.get_inputs()]
    assert names[-3:] == ["sigma_a", "sigma_s_prime", "eta"] or names[-4:-1] == ["sigma_a", "sigma_s_prime", "eta"]
    n_mat = 4 if name == "splat_materials" else 3
    base = case.test_args[:-n_mat]
    outs = {}
    for p in MATERIAL_PRESETS:
        mat = material_inputs(p, with_r_max=n_mat == 4)
        args = (*base, *mat)
        got = sess.run(None, {k: a.numpy() for k, a in zip(names, args)})
        with torch.no_grad():
            eager = case.module(*args)
        eager = eager if isinstance(eager, tuple) else (eager,)
        scale = None
        if case.scale is not None:
            with torch.no_grad():
                scale = case.scale(*args).numpy()
        e, o = eager[0].numpy().astype(np.float64), got[0].astype(np.float64)
        # texels outside the atlas charts have a zero scale and zero output: 0 / TINY32, not 0 / 0
        den = np.maximum(np.abs(e), TINY32 if scale is None else np.maximum(scale, TINY32))
        assert np.max(np.abs(o - e) / den) <= max(case.rtol, 1e-5), p
        outs[p] = o
        if name == "splat_materials":
            # the same as a module built for that material (its own r_max), not only the wrapper's eager run
            built = SplatTranslucency(DipoleMaterial.from_preset(p), window=case.module.splat.window)
            with torch.no_grad():
                ref = built(*base).numpy()
            np.testing.assert_allclose(o, ref, rtol=1e-4, atol=1e-6 * np.abs(ref).max())
    # the materials really differ in the output (the inputs are not ignored)
    a, b, c = (outs[p] for p in MATERIAL_PRESETS)
    assert not np.allclose(a, b, rtol=1e-2) and not np.allclose(a, c, rtol=1e-2)


def test_material_underflow_tail_pattern(exported):
    # Out to 150 mm skin1's blue channel goes through subnormals to 0 in float32: the pattern must agree.
    case, path, _ = exported("material")
    r = torch.linspace(0.0, 150.0, 601).reshape(-1, 1)
    with torch.no_grad():
        e = case.module(r).numpy()
    assert (e == 0).any() and ((e != 0) & (np.abs(e) < TINY32)).any()  # the check below is not vacuous
    res = compare_with_eager(case.module, path, (r,))
    assert res["zero_pattern_match"] and res["underflow_pattern_match"] and res["nonfinite_match"], res
    # and the parity holds over the whole range (the softplus parameterisation folds exactly)
    assert res["max_rel_diff"] <= RTOL, res


def test_cli_profile(tmp_path):
    out = tmp_path / "profile.onnx"
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "profile", "--out", str(out), "--opset", "18"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert out.is_file()
    assert "max abs diff" in proc.stdout and "max rel diff" in proc.stdout and "PASS" in proc.stdout


def _load_script():
    spec = importlib.util.spec_from_file_location("onnx_export_script", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_cli_list_and_bad_name(capsys):
    script = _load_script()
    assert script.main(["--list"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in EXPORTABLE)
    with pytest.raises(SystemExit) as exc:
        script.main(["no_such_module"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "no_such_module" in err and all(name in err for name in EXPORTABLE)
    with pytest.raises(SystemExit):
        script.main(["profile", "--opset", "17"])
    assert "--opset" in capsys.readouterr().err


def test_cli_all_runs_every_entry(tmp_path, monkeypatch, capsys):
    """``onnx_export.py --all`` is ``run_entry`` over the whole registry (the registry test above runs
    ``run_entry`` itself on each file): every entry is attempted, and one failure fails the run."""
    script = _load_script()
    seen = []

    def fake(name, path, *a):
        seen.append((name, Path(path).name))
        return {"name": name, "ok": name != "splat", "export_s": 0.0}

    monkeypatch.setattr(script, "run_entry", fake)
    assert script.main(["--all", "--out", str(tmp_path)]) == 1
    assert seen == [(n, f"{n}.onnx") for n in sorted(EXPORTABLE)]
    out = capsys.readouterr().out
    assert out.count("FAIL") == 1 and all(n in out for n in EXPORTABLE)
    monkeypatch.setattr(script, "run_entry", lambda name, *a: {"name": name, "ok": True, "export_s": 0.0})
    assert script.main(["--all", "--out", str(tmp_path)]) == 0


def test_export_case_unknown_name_lists_valid_names():
    with pytest.raises(ValueError, match=r"expected one of caustic_map, .*, splat_materials, got 'nope'"):
        export_case("nope")
    with pytest.raises(TypeError, match=r"name: expected a str"):
        export_case(3)


def test_export_onnx_rejects_bad_arguments(tmp_path):
    r = torch.rand(4, 1)
    m = torch.rand(3)
    path = tmp_path / "x.onnx"
    with pytest.raises(TypeError, match=r"args: expected a tuple of tensors, got a single Tensor"):
        export_onnx(DipoleProfile(), r, path)
    with pytest.raises(TypeError, match=r"args: expected a tuple of tensors, got list"):
        export_onnx(DipoleProfile(), [r, m, m, m], path)
    with pytest.raises(TypeError, match=r"args\[3\]: expected a torch.Tensor, got float"):
        export_onnx(DipoleProfile(), (r, m, m, 1.3), path)
    with pytest.raises(TypeError, match=r"module: expected a torch.nn.Module, got builtin_function_or_method"):
        export_onnx(torch.exp, (r,), path)
    with pytest.raises(ValueError, match=r"opset: expected an int >= 18.*got 17"):
        export_onnx(DipoleProfile(), (r, m, m, m), path, opset=17)
    with pytest.raises(TypeError, match=r"opset: expected an int, got float"):
        export_onnx(DipoleProfile(), (r, m, m, m), path, opset=18.0)
    with pytest.raises(ValueError, match=r"input_names: expected 4 names.*got 1"):
        export_onnx(DipoleProfile(), (r, m, m, m), path, input_names=["r"])
    with pytest.raises(ValueError, match=r"dynamic_shapes: expected 4 entries.*got 1"):
        export_onnx(DipoleProfile(), (r, m, m, m), path, dynamic_shapes=({0: torch.export.Dim("N")},))
    with pytest.raises(TypeError, match=r"path: expected a str or os.PathLike, got int"):
        export_onnx(DipoleProfile(), (r, m, m, m), 3)
    assert not path.exists()


def test_run_onnxruntime_rejects_bad_inputs(exported):
    case, path, _ = exported("profile")
    with pytest.raises(ValueError, match=r"inputs: expected 4 tensors \(r, sigma_a, sigma_s_prime, eta\), got 1"):
        run_onnxruntime(path, case.test_args[:1])
    with pytest.raises(TypeError, match=r"inputs\[1\]: expected a torch.Tensor, got list"):
        run_onnxruntime(path, (case.test_args[0], [0.1, 0.2, 0.3], *case.test_args[2:]))
    with pytest.raises(TypeError, match=r"inputs\[0\] \(r\): expected dtype float32, got float64"):
        run_onnxruntime(path, (case.test_args[0].double(), *case.test_args[1:]))
    with pytest.raises(ValueError, match=r"intra_op_threads: expected an int >= 0, got -1"):
        run_onnxruntime(path, case.test_args, intra_op_threads=-1)
    with pytest.raises(ValueError, match=r"path: expected an existing ONNX file"):
        run_onnxruntime(path.with_name("missing.onnx"), case.test_args)


def test_missing_optional_dependency_names_the_extra(monkeypatch, tmp_path):
    r = torch.rand(4, 1)
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # makes `import onnxruntime` raise ImportError
    (tmp_path / "x.onnx").write_bytes(b"")
    with pytest.raises(ImportError, match=r"torchsss\[export\]"):
        run_onnxruntime(tmp_path / "x.onnx", (r,))


def test_export_and_compare_restore_training_flags(exported):
    case, path, _ = exported("material")  # registry modules are built in training mode, the nn.Module default
    compare_with_eager(case.module, path, case.test_args)
    assert case.module.training and all(m.training for m in case.module.modules())


def test_rewrite_constant_pow_matches_pow():
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from torchsss.export import rewrite_constant_pow

    exps = [2.0, 1.5, 0.5, 3.0, 1.0, 2.5]  # 2.5 is not rewritten
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N"])
    outs = [helper.make_tensor_value_info(f"y{i}", TensorProto.FLOAT, ["N"]) for i in range(len(exps))]
    inits = [numpy_helper.from_array(np.array(e, dtype=np.float32), f"c{i}") for i, e in enumerate(exps)]
    nodes = [helper.make_node("Pow", ["x", f"c{i}"], [f"y{i}"], name=f"p{i}") for i in range(len(exps))]
    model = helper.make_model(helper.make_graph(nodes, "g", [x], outs, inits),
                              opset_imports=[helper.make_opsetid("", 18)])
    xs = np.concatenate([np.linspace(0, 50, 1001), [1e-30, 3e-39]]).astype(np.float32)

    def run(m):
        return ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": xs})

    before = run(model)
    assert rewrite_constant_pow(model) == 5
    assert [n.op_type for n in model.graph.node].count("Pow") == 1
    after = run(model)
    for e, b, a in zip(exps, before, after):
        np.testing.assert_allclose(a, b, rtol=4e-7, atol=0, err_msg=str(e))
        np.testing.assert_array_equal(a == 0, b == 0)


def test_cli_all_writes_every_entry_into_the_directory(tmp_path, monkeypatch, capsys):
    script = _load_script()
    # two cheap entries stand in for the registry (the whole registry is exported by the parametrized test above)
    monkeypatch.setattr(script, "EXPORTABLE", {n: EXPORTABLE[n] for n in ("material", "profile")})
    assert script.main(["--all", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "material.onnx").is_file() and (tmp_path / "profile.onnx").is_file()
    assert out.count("export shapes") == 2 and out.count("test shapes") == 2 and "max rel diff" in out
    assert "PASS" in out and "FAIL" not in out
    with pytest.raises(SystemExit):
        script.main(["profile", "--all"])
    assert "either NAME or --all" in capsys.readouterr().err


# -- adapters: typed errors and the truncation count in eager mode ----------------------------------------------
def test_count_truncated_agrees_with_splat_window_size():
    from torchsss.export.registry import _splat_inputs
    from torchsss.ops.splat import splat_window_size

    module = SplatTranslucency(DipoleMaterial.from_preset("skin1"), window=9)
    reach = float(module.r_max)
    seen = set()
    for size in (6, 8, 12, 20, 40, 80):
        src, _, dst, _, vp = _splat_inputs(1, size, size, 0)  # one splat: the count is 0 or 1
        need = splat_window_size(src, vp, reach, size, size)
        got = int(module.count_truncated(src, dst, vp)[0])
        assert got == int(need > 9 and size > 9), (size, need, got)
        seen.add(got)
    assert seen == {0, 1}  # both sides of the boundary were exercised
    # a window as large as the image never truncates, whatever the footprint
    src, _, dst, _, vp = _splat_inputs(5, 15, 15, 1)
    assert int(module.count_truncated(src, dst, vp, window=15)[0]) == 0 < int(module.count_truncated(src, dst, vp)[0])
    with pytest.raises(ValueError, match=r"window: expected an odd int \(the module has none\), got None"):
        SplatTranslucency(DipoleMaterial.from_preset("skin1")).count_truncated(src, dst, vp)


def test_adapters_reject_bad_modules():
    from torchsss.export import SplatExport, with_material_inputs

    with pytest.raises(TypeError, match=r"module: expected a SplatTranslucency, got DipoleProfile"):
        SplatExport(DipoleProfile())
    with pytest.raises(ValueError, match=r"window=K"):
        SplatExport(SplatTranslucency(DipoleMaterial.from_preset("skin1")))
    two = SplatTranslucency([DipoleMaterial.from_preset("skin1"), DipoleMaterial.from_preset("marble")], window=5)
    with pytest.raises(ValueError, match=r"expected one material, got a table of 2"):
        SplatExport(two)
    with pytest.raises(ValueError, match=r"expected exactly one DipoleMaterial .* got 0"):
        with_material_inputs(DipoleProfile())
    with pytest.raises(ValueError, match=r"expected exactly one DipoleMaterial .* got 2"):
        with_material_inputs(two)
    with pytest.raises(ValueError, match=r"inputs: expected distinct identifiers"):
        with_material_inputs(DipoleMaterial.from_preset("skin1"), inputs=("eta",))
    m = SplatExport(SplatTranslucency(DipoleMaterial.from_preset("skin1"), window=5), material_inputs=True)
    from torchsss.export.registry import _splat_inputs

    with pytest.raises(ValueError, match=r"r_max: expected tensors \(material_inputs=True\), got None"):
        m(*_splat_inputs(3, 8, 8, 0))


def test_material_inputs_wrapper_leaves_the_module_alone_and_follows_its_inputs():
    from torchsss.export import with_material_inputs

    mat = DipoleMaterial.from_preset("skin1")
    wrapped = with_material_inputs(mat)
    r = torch.linspace(0, 20, 50).reshape(-1, 1)
    for name in MATERIAL_PRESETS:
        with torch.no_grad():
            got = wrapped(r, *material_inputs(name))
            want = DipoleMaterial.from_preset(name)(r)
        torch.testing.assert_close(got, want, rtol=2e-6, atol=0)
    assert isinstance(mat, DipoleMaterial) and type(mat) is DipoleMaterial  # the original is not swapped
    with torch.no_grad():
        torch.testing.assert_close(mat(r), DipoleMaterial.from_preset("skin1")(r))
