"""The planner: the method, knobs and modelling a scene needs to meet an error tolerance at least cost.

``plan(scene, tolerance=0.02, frames=1)`` looks at the scene in closed form (:class:`SceneFacts`: each channel's
scattering length :math:`1/\\sigma_{tr}` and :math:`r_{max}(\\epsilon)` against the object's size, the camera's
pixel footprint on the surface, the mesh's faces and edges, whether the object is convex, how many pixels it
covers), predicts for every candidate configuration of every applicable method its error against the reference
and its setup and frame time (:func:`predict`), and returns the cheapest candidate whose predicted error meets the
tolerance (setup + ``frames`` x frame time: a method with costly setup and cheap frames wins only when many
frames follow) as a :class:`Plan`, with a one-line reason for every choice.

The predictions are closed forms of the scene facts with constants fitted to the measured trade
(:mod:`torchsss.trade`; :data:`MODEL` says which rows), verified on other scenes by
``benchmarks/bench_planner.py``. Two facts carry most of the scene dependence: ``unlit`` (how much of the view faces
away from the light: back-lit views show light that crossed the object, the far field that truncation and sampling
miss) and :func:`depth` (the object's thickness in scattering lengths, weighted by ``unlit``):

* reference: none with the truth's own sources; otherwise a floor (a resampled source set) plus a term linear in
  how much coarser its effective spacing :math:`\\sqrt{A / n}` is than the truth's (every face holds at least one
  sample, so a fine mesh samples finer than asked, and a coarser ``eps`` may keep most sources) and the sources'
  lattice error :func:`~torchsss.physics.splat_alias_error`, plus, for sources on a decimated mesh, how far that
  mesh strays from the surface over :math:`1/\\sigma_{tr}` (:func:`~torchsss.geometry.mesh.surface_deviation`);
  time ~ covered pixels x sources.
* splat: a floor, a truncation term ~ ``eps`` growing with ``unlit`` and ``depth``, and a light-view sampling term
  ~ 1/oversample^2 weighted by how bright the channels it aliases are; time ~ splats x footprint pixels.
* icdf / hybrid: Monte Carlo, :math:`a\\,N^{-p}` (:func:`sampling_terms`) with ``a`` growing with ``unlit`` and
  ``depth`` and, for icdf, with the scene's one-sample spread :func:`sampling_spread` (the relative deviation of one
  irradiance-importance sample of the seen radiosity, in closed form on the faces; hybrid: plus its split's floor);
  time ~ pixels x N. The hybrid's surface local term adds its pairs (covered pixels x the samples
  within the local bound, at the pixel stride the renderer would pick, :func:`hybrid_local_plan`) to setup and
  frame; where they do not fit even at stride 8 the renderer narrows the split (:func:`hybrid_split_plan`), and the
  hybrid is predicted with the larger of its own error and the icdf estimator's on the near field it then samples
  (the narrowed split's one-sample spread; :func:`hybrid_error`); where the split is off it is the icdf estimator.
* lensch: a floor plus a texel-size term; setup (atlas, kernels, throughput,
  blending) dominates.

A candidate qualifies when its predicted error times its method's margin (:data:`MARGINS`, from leave-one-scene-out
cross-validation of these constants) meets the tolerance. The reference, icdf and hybrid frames run in the compiled
pair sum of :mod:`torchsss.ops.fused` (splat's gather too): a frame big enough to compile is charged one compile in
the setup unless this process has already compiled that kernel (:func:`warm_kernels`; a shorter one where it has
compiled another variant), and none under ``TORCHSSS_COMPILE=off``.

"Model only what a scene requires" (:data:`RULES`, each reported in ``Plan.reasons`` when it applies):

* ``decimate``: the atlas methods get the mesh decimated to the detail the pixel footprint and the shortest
  scattering length can show (a 268k-face scan does not need 268k faces for an atlas).
* ``sources``: the reference's sources come from the mesh decimated to its sample spacing (``source_faces``).
* ``shadows``: no shadow rays when nothing can occlude the light (a convex object: n.l > 0 is visibility).
* ``samples``: the icdf/hybrid sample count N from the tolerance (error ~ N^-p).
* ``splat_budget``: the splat tolerance and grid oversampling from the tolerance (Shah eq. 6.16-6.18).
* ``blend``: Lensch's blending only where the planned kernel reaches the neighbouring vertices
  (:func:`~torchsss.geometry.lensch.plan_lensch`).
* ``reference``: the reference itself when it is the cheapest way to the tolerance (tiny images, tiny meshes).
* ``compile``: one compile of the fused pair sum, unless this process has compiled it already.
* ``local_term``: the hybrid without a split (its local bound reaches across the object) is the icdf estimator;
  one whose split narrows because its local pairs cannot fit samples the near field it gives up: N planned with
  the larger of its own error and the icdf estimator's on that part (:func:`hybrid_split_plan`,
  :func:`hybrid_error`).

Lengths are millimetres, times seconds (of the calibration machine, one thread).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar, NamedTuple

import numpy as np
import torch

from torchsss._checks import validation
from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.lensch import (
    ATLAS_UTILIZATION,
    BLEND_MIN_REACH,
    MAX_THROUGHPUT_ENTRIES,
    THROUGHPUT_THRESHOLD,
    estimate_throughput_entries,
    throughput_cut,
)
from torchsss.geometry.lights import DirectionalLight, PointLight, SpotLight, incident_light
from torchsss.geometry.mesh import CREASE_DEG, Mesh, check_mesh, surface_deviation
from torchsss.geometry.sampling import faces_for_spacing
from torchsss.modules.chang import ChangLocalProfile, SplitProfile
from torchsss.modules.material import bulk_profile, material_module
from torchsss.ops.fused import block_shape, compile_policy, is_warm
from torchsss.ops.splat import GATHER_REACH
from torchsss.physics.budget import chang_rp, profile_tail_fraction, splat_alias_error, splat_spacing
from torchsss.physics.dipole import total_diffuse_reflectance
from torchsss.physics.materials import Material
from torchsss.pipelines.atlas_view import source_mesh
from torchsss.pipelines.chang import LOCAL_STRIDES, HybridRenderer, profile_rp
from torchsss.pipelines.splat import MIN_GRID, grid_for, light_sources
from torchsss.scene import Scene
from torchsss.trade import ATLAS_METHODS, applicable_methods

__all__ = ["MARGINS", "MODEL", "RULES", "Plan", "SceneFacts", "candidates", "hybrid_error", "hybrid_local_bound",
           "hybrid_local_plan", "hybrid_split_plan", "plan", "plan_method", "predict", "warm_kernels"]

#: The rules the planner applies (name -> what it skips or chooses).
RULES = {
    "decimate": "atlas methods: decimate the mesh to the detail the pixel footprint and the scattering length show",
    "sources": "reference: sample sources from the mesh decimated to the sample spacing",
    "shadows": "reference: no shadow rays when nothing occludes the light (convex object)",
    "samples": "icdf/hybrid: N from the tolerance (error ~ N^-p; icdf's times the scene's one-sample spread^1.5)",
    "splat_budget": "splat: the budget's tolerance and the grid from the tolerance",
    "blend": "lensch: blending only where the kernel reaches the neighbouring vertices",
    "creases": "lensch: charged the irradiance's detail where creases meet (light entering a slab's rim)",
    "threshold": "lensch: a finer throughput threshold only where the default cuts light the seen side needs",
    "reference": "the reference itself when it is the cheapest way to the tolerance",
    "compile": "reference/icdf/hybrid/splat's gather: one compile of the fused pair sum, unless this process already "
               "compiled it (less where it compiled another variant)",
    "local_term": "hybrid: its local term's pairs costed; no split planned as the icdf estimator, a narrowing one "
                  "also bounded by the icdf estimator on the near field it samples",
}

#: Constants of the predictions (see :func:`predict` for the forms). The error constants are fitted by
#: ``benchmarks/fit_planner.py`` to the measured trade of 7 calibration scenes (``results/trade/*/trade.json``,
#: ``results/planner_v1_rows.json``; under-prediction weighted 10x). The time constants were refitted
#: (``fit_planner.py --times-only``, 2026-11-25) to the four calibration trades re-measured with the current code,
#: warm (the truth compiles the fused pair sum first), 1 thread on this shared 2-core machine; ``splat_t_texel`` and
#: ``icdf_s0`` kept their earlier values (the free fit drove them below 1% of those). Times in seconds. The hybrid
#: error constants were refitted after its local filter became 8 x 16, and the hybrid's and Lensch's again on
#: 2026-11-26 (``bench_trade.py --methods lensch hybrid``: the hybrid's surface local term and Lensch's unblended
#: hat quadrature had made the earlier floors, 2.95% and 8.47%, stale; Lensch's error gained a blending term); the
#: other methods kept theirs.
MODEL: dict[str, float] = {
    # reference: frame = t_pair * pairs + t_src * sources * lights + t_px * pixels; setup = s0 + s_src * sources;
    # error = 0 with the truth's sources, else err_floor + err_n * (h / h0 - 1) + err_alias * hypot(alias(h),
    # alias(h0)) with h, h0 the effective spacings sqrt(A / n) of the sources and of the truth's (h0 at least base x
    # the truth's asked spacing), plus a decimated surface's deviation (not fitted). Fitted 2026-11-27 (session 9)
    # on the 34 scenes of splat's fit below: the model had charged err_eps * (eps - 0.01), 1.4% at eps 0.3 on every
    # scene, where 0-1.34% was measured (none at all where every face already holds a source, 0.05% on the
    # side-lit 80 mm ketchup spot)
    # The frame's time constants refitted 2026-11-29 (fit_planner.py --times-from: setup + one frame of the 84
    # reference rows of two verification runs, 1 thread, two runs side by side, the pairs counted in the compiled
    # sum's whole blocks): fused_t_pair 9.14e-9 -> 3.53e-8 (28 Mpairs/s in all; the plain kernel alone measured 35-48
    # that day), t_src 1.06e-5 -> 1.06e-9 (the fit cannot tell the shadow rays per source from the pairs per
    # source: both scale with the sources), t_px 1.21e-5 -> 5.52e-6; predicted / measured median 0.52 -> 0.98
    "ref_t_pair": 3.0e-7, "ref_t_src": 1.06e-09, "ref_t_px": 5.52e-06, "ref_s0": 0.0102, "ref_s_src": 5.77e-06,
    "ref_err_floor": 0.00241, "ref_err_n": 0.00463, "ref_err_alias": 1.0, "ref_base": 0.2,
    # splat: frame = pairs + t_texel * grid^2 * lights + f0, with splats = light_fill * grid^2 (SceneFacts) and the
    # pairs either compiled, t_gather * (covered px x splats in whole blocks) * lights where splat_radiosity picks its
    # gather (a reach share of GATHER_REACH and the truncated pair sum compiled or worth compiling), or eager,
    # t_splat * splats * min(px, footprint_px) * lights (the window and tile paths). Measured 2026-11-29 (1 thread,
    # 108 frames of the 18 scenes of two verification sets, every path timed inside splat_radiosity): the gather
    # 1.75e-8 s per blocked pair (median; 1.4-2.5e-8 p10-p90), the eager paths 0.9-4.5e-7 (median 1.4e-7), the rest
    # of a frame 0.134 s + 1.56e-6 s per texel of grid^2, the setup 0.17 s (median). They had been t_splat 5.09e-8
    # for every frame at 0.5 grid^2 splats, t_texel 2e-5, f0 0.114, s0 0.2: a back-lit 20 mm potato sphere at
    # oversample 2 predicted 0.45 s, measured 3.3-4.6 s (eager), a 256 x 256 gather 8.9 s (a first compile charged
    # after the truth's), measured 1.3-1.7 s
    "splat_t": 1.5e-07, "splat_t_gather": 1.75e-08, "splat_t_texel": 1.56e-06, "splat_f0": 0.134, "splat_s0": 0.17,
    # error = hypot(floor * u^u_floor, max(trunc * u^u_trunc * d^q_depth, 1) * cut, alias * u^u_alias * w / s^2,
    #               obj * [convex: obj_convex] * (32 / grid)^obj_p)
    # with cut the profile's energy between r_max(eps) and the object's diameter (at most eps: the truncation drops
    # it from every splat whatever the light; nothing when r_max spans the object), s the light view's texels
    # per splat spacing as built (the grid clamped to [32 x oversample, 512]) and w the share of that aliasing the
    # image sees (_Profile.alias_share: the grid follows the finest channel, the image's error the brightest), u =
    # max(unlit, 0.1), d = 1 + u * thickness * sigma_tr,min (light that crossed the object: the far field).
    # Fitted 2026-11-27 (session 9) on 34 scenes (the 7 calibration scenes and the 27 of four verification runs,
    # results/planner_v1_rows.json .. planner_v4_rows.json). Without w the aliasing term had predicted 3-6x the
    # measured error of ketchup at oversample 1 (the side-lit 80 mm spot at eps 0.01: 6.5% predicted by the
    # earlier constants, 1.9% measured; now 1.8%), which kept splat out of the plans where it was 4-6x faster than
    # the reference
    # refitted 2026-11-28 (fit_planner.py --methods splat) to splat's calibration rows alone
    # (results/splat_calibration_rows.json: the 30 scenes of the verification rows and the 4 calibration trades'
    # re-rendered at oversample 1, 2, 4 and 8 after the light view's flux began to follow the shading normals,
    # torchsss.geometry.shading_flux). The floor had been 1.48% u^0.038, set by scans that stayed 1.2-1.5% off at
    # every oversampling with the faces' projected area; now 1.17% u^0.2 (0.65% front-lit, 1.0% side-lit, 1.16%
    # back-lit). Earlier constants: floor 0.0148, trunc 1.04, alias 0.146, u_floor 0.0378, u_trunc 2.48, u_alias
    # 0.548, q_depth 2.2 (u_trunc and q_depth are now at the fit's bound of 3)
    # Refitted 2026-11-29 with the obj term, after the light view's floor began to scale with the oversampling
    # (splat.MIN_GRID; the rows re-measured, results/splat_calibration.md): what the floor had stood for on small or
    # long-scattering objects was their light view clamped at 32 texels at every oversampling (a side-lit 8 mm
    # potato torus 1.92% at every configuration; 0.93 / 0.53 / 0.30% at 64 / 128 / 256). Floor 1.17% u^0.2 -> 0.47%
    # u^0.56; obj 1.58% (32 / grid)^0.67 on objects that are not convex, none on convex ones (fitted to the bound:
    # spheres and slabs measured 0.14-1.03% at 32 texels, 0.05-0.35% at 64). In sample at margin 1.1, 598
    # configuration x tolerance pairs accepted, 9 falsely, where the constants before accepted 516 (7). Earlier
    # constants: floor 0.0117, trunc 0.646, alias 0.148, u_floor 0.197, u_trunc 3.0, u_alias 0.503, q_depth 2.9
    # Since 2026-11-29 the truncation is computed on the scene (SceneFacts.splat_truncation, truncation_error), no
    # longer the planar tail times a fitted max(0.674 u^3 d^2.89, 1): that term over-predicted 3-10x (the default
    # scene at eps 0.003: 2.8% charged, 0.25% computed, 0.63% measured in all)
    "splat_floor": 0.00467, "splat_alias": 0.181, "splat_u_floor": 0.557, "splat_u_alias": 0.676,
    "splat_obj": 0.0158, "splat_obj_p": 0.674, "splat_obj_convex": 3e-05,
    # icdf/hybrid: frame = t_pair * pixels * N + f0; setup = s0 + s_face * faces + s_texel * res^2;
    # error = hypot(floor (hybrid: * u^u_floor), a * [icdf: q^q_spread] * u^u * d^q_depth * (4096 / N)^p).
    # icdf refitted 2026-11-27 (session 10) with the one-sample spread q (SceneFacts.sampling_spread) on the 34
    # scenes' rows less those with a scene-level decimation (fit_planner.SEEN_FULL): predicted/measured 0.74-2.04
    # (median 1.18) where the constants without q (a 0.143, u 1.57, q_depth 0.278, p 0.802, floor 0.00315) spanned
    # 0.16-45 (median 1.69) and accepted 35 (row, tolerance) pairs at margin 1 against 138 now
    # setup = s0 + s_face * faces^face_p + ...: refitted 2026-11-29 (fit_planner.py --times-from, the 36 icdf rows
    # of the main and fresh verification runs, setup + one frame): s_face 2.38e-6 at face_p 1 had predicted a
    # 20,000-face mesh's atlas and sampler in 0.35 s where 11-26 s were measured (1-6k faces: 1.2-3.5 s in all), so
    # the planner put icdf on a 30k-face back-lit ketchup bunny at 1% for 1.7 s predicted, measured 38 s
    # (now 9.17e-6 faces^1.42: 20k faces 12 s; s0 0.3 and f0 0.433 went to about 0, the hybrid's s0 0.275 to 0.631;
    # predicted / measured median 0.81-0.89 -> 1.05-1.08, p10-p90 0.15-1.47 -> 0.56-1.64)
    "icdf_t_pair": 1.9e-7, "icdf_f0": 0.00194, "icdf_s0": 3e-05, "icdf_s_face": 9.17e-06, "icdf_face_p": 1.42,
    "icdf_s_texel": 2.61e-06,
    "icdf_a": 0.00283, "icdf_p": 0.782, "icdf_floor": 0.00197, "icdf_u": 0.385, "icdf_q_depth": 0.0882,
    "icdf_q_spread": 1.5,
    "hybrid_t_pair": 1.8e-7, "hybrid_f0": 0.693,
    "hybrid_s0": 0.631, "hybrid_a": 0.00725, "hybrid_p": 0.846, "hybrid_floor": 0.0121, "hybrid_u": 1.94,
    "hybrid_u_floor": 0.196, "hybrid_q_depth": 1.13,
    # the hybrid's surface local term (hybrid_local_plan): per pair, the first frame of a view lists the pairs and
    # their weights (k-d tree and profile), every frame sums them; at stride > 1 about half the covered pixels are
    # refined exactly, their pairs listed, weighted and summed in that frame (measured 2026-11-26 at 128 x 128, 1
    # thread: the default scene 4.5M pairs, 0.24 s a frame; the side-lit marble torus 5.5M pairs at stride 2 and
    # 2,212 of 3,640 pixels exact, 3.2 s; the cream spot 55% exact)
    "hybrid_t_local": 5.2e-8, "hybrid_t_local_build": 3.2e-7, "hybrid_t_exact": 3.0e-7,
    "hybrid_exact_fraction": 0.5, "hybrid_local_edge": 14.6, "hybrid_local_headroom": 2.0,
    # lensch: frame = t_texel * res^2 + f0; setup = s0 + s_face * faces + s_kernel * res^2 * k^2 (blending);
    # error = hypot(floor, c * (texel / (1/sigma_tr)_min)^3, blend when blending): since the unblended kernels
    # answer only the irradiance's detail (hat quadrature), the unblended build is the accurate one (re-measured
    # 2026-11-26, four calibration scenes at 96 x 96: unblended 0.20-2.04%, blended 1.8-20%, the blended atlas 512
    # 2.0-6.6% where the unblended 1024 measured 0.20-2.04%). s_kernel: the blending fit per face pair, only when
    # blending (1.7e-7 measured on the default scene at atlas 512, k = 11: 5.5 s; 2x for load). The frame constants
    # refitted 2026-11-27 (fit_planner.py --times-only --methods lensch on the re-measured calibration rows, after the
    # valid-texel irradiance atlas and the depth-only shadow maps: predicted / measured frame 0.75-1.34; they were
    # 1.41e-6 and 0.229); the setup constants kept (the free fit of 16 rows moved s_face 12x)
    "lensch_t_texel": 2.91e-07, "lensch_f0": 0.0966, "lensch_s0": 3.23, "lensch_s_face": 2.04e-05,
    "lensch_s_kernel": 2.92e-06, "lensch_floor": 0.0175, "lensch_texel": 0.126, "lensch_blend": 0.083,
    # lensch's first frame after a build (or a material edit) evaluates the profile at every throughput entry and
    # kernel tap: t_entry * entries + t_tap * res^2 * k^2, charged with the setup (the calibration trades time
    # the median frame, without it). Measured 2026-11-27 (benchmarks/bench_lensch_memory.py, 1 thread, the
    # default scene, the profile through bulk_profile's tables): 1.59 s for 6.36M entries with the hat quadrature
    # at atlas 1024; the kernel planes 1.53 s at 1024 (unblended: k = 7, the symmetric half planes) and 1.68 s at
    # 512 (blended, k = 11, full planes): 3.0e-8 and 5.3e-8 s per texel and tap. Checked on the shared bunny and
    # igea at atlas 1024 (6,744 and 5,874 source faces): 3.5 and 3.6 s predicted, 3.56 and 3.28 s measured
    "lensch_t_entry": 2.5e-07, "lensch_t_tap": 3.0e-08, "lensch_t_tap_full": 5.3e-08,
    # the fused dipole pair sum (torchsss.ops.fused, compiled; reference, icdf and hybrid frames of >= COLD_WORK pairs;
    # the hybrid's split variant: 44 Mpairs/s warm on the default scene at 128^2, 1 thread):
    # seconds per pair at 1 thread, the pairs counted in whole blocks (_blocked; refitted 2026-11-29 with the
    # reference's frame constants above: 3.53e-8, 28 Mpairs/s, where 9.14e-9 (109 Mpairs/s, fitted 2026-11-25 on the
    # warm calibration rows) had under-predicted the reference's frames 2-4x since; icdf's and the hybrid's frames,
    # which share it, predicted / measured median 0.52-0.56 -> 0.73-0.89) and one cold compile with an empty
    # inductor cache (6.0-7.0 s measured on a quiet machine since the compile trusts the CPU's ISA flags,
    # torchsss.ops.fused._compile_config; 12-13 s before; 11 s on 2026-11-29)
    "fused_t_pair": 3.53e-08, "fused_compile_s": 7.0,
    # a further variant of the pair sum (plain, split, truncated) in a process that has compiled one: measured
    # 2026-11-29, 1 thread, splat's truncated gather after the reference's plain sum, 0.27 s with the graph in
    # inductor's disk cache (the blocks' shapes are static: every process compiles the same graphs, so after a
    # machine's first render it holds them) and 5.8 s with an empty cache, where the first compile took 5.3 s and
    # 11 s; charged 1 s (it had been charged the first compile's 7 s: a 256 x 256 splat gather after the truth
    # was predicted at 8.9 s and measured 1.3-1.7 s)
    "fused_variant_s": 1.0,
    # decimation (quadric edge collapse): seconds per input face
    "decimate_s_face": 4.0e-6,
    # an atlas built on a decimated mesh has its valid texels (about 0.6 of the square) moved to their closest points
    # on the full mesh once, to be lit there (AtlasView.lit_texels; 1 thread, 2026-11-27: 0.49-2.07 s for 139k-637k
    # texels on the shared bunny and igea, 3.2-3.7e-6 s a texel)
    "transfer_s_texel": 3.3e-6,
    "valid_fraction": 0.6,
}

#: Safety factor: a candidate qualifies when its predicted error times this is within the tolerance. The smallest
#: that accepts no configuration of the calibration rows whose measured error exceeds the tolerance (1%, 2%, 5%):
#: at 1.0, 4 of 178 accepted rows were false; at 1.1, none of 164 (``benchmarks/fit_planner.py``). In-sample: the
#: floor of :data:`MARGINS`.
MARGIN = 1.1
#: Per-method safety factors from leave-one-scene-out cross-validation (``benchmarks/fit_planner.py --cv``: the
#: constants refitted without a calibration scene, that scene's rows predicted): the smallest margin at which at
#: most 5% of the held-out configurations accepted for a tolerance (1%, 2%, 5%) miss it, and at least
#: :data:`MARGIN`. Since icdf's error model knows the scene's one-sample spread (2026-11-27, session 10) its held-out
#: errors carry as well as the others': icdf 1 of 137 accepted configurations missed at 1.1 (without it, 3 of 34 at
#: 1.1 and 1 of 28 at 1.75), none of 120 at 1.5; the hybrid 2 of 165 at 1.1 and 1 of 161 at 1.25 (its unsplit rows
#: use the icdf model); the reference 4 of 461 and splat 11 of 259 at 1.1 (both refitted 2026-11-27 on 34 scenes);
#: Lensch 1 of 8 at 1.1, 0 of 5 at 1.25 (results/planner_cv.json). The Monte Carlo estimators keep more: their
#: misses are noise that a default render shows in every frame. icdf takes its margin with no held-out miss (1.5):
#: at 1.1 its default knobs for 3% measured 3.54% on the spread's back-lit 30 mm marble bunny at 256 x 256 (2.69%
#: predicted; a scene without calibration rows of icdf). The hybrid keeps the 1.25 it had (1 of 161 held out missed;
#: none at 1.75, which would put its floor times the margin over a 2% tolerance on back-lit scenes: 1.21% x 1.75).
#: Splat's was raised from 1.1 to 1.5 on 2026-11-29, when its time model began to predict its frames (predicted /
#: measured median 0.87-0.91, 0.2-0.5 before on the scenes where it is eager or gathers) and the planner picked it
#: more: a verification run of the first two sets then missed 4 of 54 pairs, all splat on the side-lit 12 mm
#: whole-milk torus (1.46%, 3.48% and 7.99% at 1%, 2% and 5%) and the back-lit 60 mm whole-milk sphere (5.86% at
#: 5%): the planner takes the cheapest configuration that qualifies, which is the likeliest false accept. In sample
#: (the 34 calibration scenes' splat rows), margin 1.1 accepts 598 configuration x tolerance pairs, 9 falsely, every
#: one on those two scenes (the model misses how a long-scattering material's thin ring aliases at the object's
#: scale, and the tail that light crossing a 60 mm sphere arrives by); 1.25 accepts 569 (6), 1.5 527 (2, both the
#: sphere at eps 0.003, oversample 4 and 8, 5.64% for 2.17% predicted: a truncation the model under-predicts).
MARGINS = {"reference": 1.1, "splat": 1.5, "icdf": 1.5, "hybrid": 1.25, "lensch": 1.25}
#: The reference's sources per face of a mesh decimated to its spacing (a decimated 81920-face sphere at
#: 8 A / h^2 faces gave 1.15).
SOURCES_PER_FACE = 1.2
#: The truth's tolerance (the reference's default ``eps``).
TRUTH_EPS = 0.01
#: The longest edge (in pixel footprints) the decimation rule leaves on a mesh the camera sees.
MAX_EDGE_PX = 3.0
#: The light view :attr:`SceneFacts.light_fill` counts splat's sources at (texels across the object; 5-40 ms a light
#: on the 2-40k-face meshes of the verification scenes).
FILL_GRID = 32
#: The fewest icdf/hybrid samples the planner plans: the smallest N of the calibration sweeps (the N^-p law is not
#: extrapolated below it; at N = 512 the front-lit 80 mm ketchup teapot measured 3.19% where 2.06% was predicted).
MIN_SAMPLES = 1024.0
#: The splat budget tolerances the planner considers.
SPLAT_EPS = (0.003, 0.01, 0.03)
#: The light view oversamplings splat is planned at. 1.5 sits between the calibrated 1, 2 and 4 (the error model is
#: continuous in the texels per splat spacing): where oversample 1 is predicted to miss and 2 meets with room, 1.5
#: holds 2.25x oversample 1's splats where 2 holds 4x (added 2026-11-29: of the 34 planned renders of all four
#: verification sets that ran over 1.5x the fastest configuration meeting their tolerance because another
#: configuration was chosen, 20 were beaten by splat at oversample 1, 12 of them planned at oversample 2 or 4)
SPLAT_OVERSAMPLE = (1.0, 1.5, 2.0, 4.0)
#: Lensch's throughput thresholds the planner considers: the default, and finer ones where the default cuts light
#: the image needs (:attr:`SceneFacts.throughput_cut`).
LENSCH_THRESHOLDS = tuple(float(f"{THROUGHPUT_THRESHOLD * f:.3g}") for f in (1.0, 0.1, 0.01))
#: The cut (a share of the image's radiosity) above which the planner offers Lensch the finer threshold: 0.1% (on
#: the verification scenes the default cuts at most 0.09% but on the back-lit 60 mm whole-milk sphere, 4.6%).
CUT_MATTERS = 0.001
#: The reference tolerances the planner considers (the first is the truth).
REFERENCE_EPS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3)


@dataclass(frozen=True)
class SceneFacts:
    """What the planner knows about a scene in closed form (mm, mm^-1; pixels).

    Attributes:
        faces: the mesh's face count.
        size_mm: the bounding box's diagonal.
        area_mm2: surface area.
        radius_mm: bounding-sphere radius (max vertex distance from the box centre).
        median_edge_mm: median edge length.
        convex: the mesh's volume is at least 98% of its convex hull's (nothing occludes the light).
        thickness_mm: mean chord length :math:`4V/S` (how thick the object is for light passing through; on a mesh
            that is not watertight, :math:`V` is its divergence-theorem volume bounded by its convex hull's).
        pixel_mm: the camera's pixel footprint at the object's nearest distance.
        covered_px: pixels the object covers (Cauchy: the hull's mean projected area is a quarter of its area;
            at the centre's distance).
        pixels: the image's pixel count.
        lights: number of lights.
        unlit: how much of the object the camera sees lies away from the light, in [0, 1]: per light
            :math:`(1 - \\cos\theta) / 2` with :math:`\theta` between the directions from the centre to the eye and
            to the light, weighted by the light's irradiance at the centre (0 front-lit, 0.5 side-lit, 1 back-lit).
            Back-lit views show light that crossed the object: the far field, which truncation and sampling miss.
        ell_mm: per channel :math:`1/\\sigma_{tr}`.
        r_max_mm: per channel :math:`r_{max}` at :data:`TRUTH_EPS`.
        spacing_mm: the truth reference's sample spacing.
        sources: the reference's source count on the full mesh at each of :data:`REFERENCE_EPS`.
        source_faces: per :data:`REFERENCE_EPS`, the face count the sources need (:func:`source_faces`).
        sources_decimated: per :data:`REFERENCE_EPS`, the source count on the mesh decimated to ``source_faces``
            (about 1.2 per face: a decimated 81920-face sphere at 8 A / h^2 faces gave 1.15).
        source_deviation_mm: per :data:`REFERENCE_EPS`, how far the mesh decimated to ``source_faces`` strays from
            the surface (:func:`~torchsss.geometry.mesh.surface_deviation`, 90th percentile; 0 where the sources
            would not be decimated).
        local_bound_mm: the hybrid's local bound :math:`r_b` at its default split (:func:`hybrid_local_bound`; 0
            when the split is off because :math:`r_b` exceeds 0.8 times the object's radius).
        atlas_deviation_mm: how far the mesh decimated to :func:`detail_faces` (the atlas methods' mesh) strays
            from the surface (90th percentile, as ``source_deviation_mm``; 0 where it is not decimated).
        irradiance_detail: the irradiance's detail at the scale of the vertex hats (:func:`irradiance_detail`):
            what Lensch's vertex hats cannot follow (parted at creases they carry the irradiance's jump, but the
            radiosity beside the crease varies as sharply and is interpolated over them) and its texture-space
            kernels cannot reach across a chart seam (light entering a slab's rim).
        throughput_entries: Lensch's vertex throughput entries on the full mesh at its default threshold
            (:func:`~torchsss.geometry.lensch.estimate_throughput_entries`; -1 when not estimated: ``from_scene``
            with ``throughput=False``, for plans that cannot pick Lensch); they scale with the square of the
            vertex count where the profile reaches across the object.
        throughput_cut: per threshold of :data:`LENSCH_THRESHOLDS`, the share of the image's radiosity that
            Lensch's throughput threshold cuts (:func:`~torchsss.geometry.lensch.throughput_cut`: light that
            reaches the seen side only along entries below the threshold, as through a large back-lit object of a
            long-scattering material), on the mesh decimated as Lensch's throughput needs; () when not estimated.
        throughput_entries_finer: the full mesh's entries at the finer thresholds (``LENSCH_THRESHOLDS[1:]``),
            estimated only where the default threshold cuts enough to matter (:data:`CUT_MATTERS`); () otherwise.
        sampling_spread: the relative standard deviation of one irradiance-importance sample of the radiosity the
            camera sees (:func:`sampling_spread`): the icdf estimator's noise at one sample, from where the light
            enters against where the camera looks; -1 when not computed (``from_scene`` with ``spread=False``, for
            plans that cannot pick icdf or the hybrid).
        local_samples: the hybrid's surface local samples (its mesh decimated to the truth's spacing, as
            :func:`~torchsss.pipelines.chang.build_hybrid` samples it; 0: the full mesh's ``sources[0]``).
        narrowed_bounds_mm: the hybrid's local bound at Chang's importance bound ``c`` times 2, 4, 8, 16 (the
            renderer narrows the split in these steps when the pairs do not fit; 0 where the split narrows away);
            computed only where the default split's pairs do not fit (() otherwise).
        narrowed_spread: the one-sample spread (:func:`sampling_spread`) of the global part of the split the
            renderer is predicted to narrow to (:func:`hybrid_split_plan`), which samples more of the near field;
            ``sampling_spread`` where it does not narrow (-1 when not computed).
        light_fill: splat's sources per texel of its light view (a square of the bounding sphere's diameter): the
            share of the texels that see the object, plus the pieces grazing light cuts them into
            (:func:`~torchsss.geometry.grazing.split_grazing`), as the renderer makes them at a light view of
            :data:`FILL_GRID` texels, averaged over the point, spot and directional lights (about :math:`\\pi / 4`
            on a sphere lit face-on; 0.5 when there are none). Splat's frame time follows its sources.
        splat_truncation: what splat's truncation at :math:`r_{max}(\\epsilon)` drops from the seen radiosity, per
            :data:`SPLAT_EPS` (:func:`truncation_error`, closed form on the faces; 0 where :math:`r_{max}` spans the
            object; () when not computed: the planar tail to the object's diameter is charged instead).
    """

    faces: int
    size_mm: float
    area_mm2: float
    radius_mm: float
    median_edge_mm: float
    convex: bool
    thickness_mm: float
    pixel_mm: float
    covered_px: float
    pixels: int
    lights: int
    unlit: float
    ell_mm: tuple[float, float, float]
    r_max_mm: tuple[float, float, float]
    spacing_mm: float
    sources: tuple[int, ...]
    source_faces: tuple[int, ...]
    sources_decimated: tuple[int, ...]
    throughput_entries: int
    source_deviation_mm: tuple[float, ...] = ()
    local_bound_mm: float = 0.0
    atlas_deviation_mm: float = 0.0
    irradiance_detail: float = 0.0
    throughput_cut: tuple[float, ...] = ()
    throughput_entries_finer: tuple[int, ...] = ()
    sampling_spread: float = 1.0
    local_samples: int = 0
    narrowed_bounds_mm: tuple[float, ...] = ()
    narrowed_spread: float = 1.0
    light_fill: float = 0.5
    splat_truncation: tuple[float, ...] = ()

    @classmethod
    def from_scene(cls, scene: Scene, mesh: Mesh | None = None, *, throughput: bool = True,
                   spread: bool = True) -> SceneFacts:
        """Compute the facts of a single-object scene (loads the mesh unless given).

        ``throughput``: estimate Lensch's throughput size (70% of the facts' time on a 5k-face mesh). ``spread``:
        compute the icdf estimator's one-sample spreads (``sampling_spread``, ``narrowed_spread``: 0.15 of the
        0.25 s a 2k-face torus's facts take). The facts of the last few (scene, mesh) pairs are kept: planning the
        same scene for another tolerance or frame count reuses them (0.3-0.7 s on a 40k-face scan), and facts kept
        without the spreads gain them when asked.
        """
        mesh = scene.load_mesh(dtype=torch.float64) if mesh is None else mesh
        key = (hash(scene), id(mesh))
        hit = _FACTS.get(key)
        if hit is not None and hit[0] is mesh and hit[1] == scene and (hit[2].throughput_entries >= 0
                                                                       or not throughput):
            if hit[2].sampling_spread >= 0 or not spread:
                return hit[2]
            facts = cls._spreads(scene, mesh, hit[2])
        else:
            facts = cls._compute(scene, mesh, throughput, spread)
        if len(_FACTS) >= 8:
            _FACTS.pop(next(iter(_FACTS)))
        _FACTS[key] = (mesh, scene, facts)  # the mesh is held, so its id is not reused while the entry lives
        return facts

    @classmethod
    def _spreads(cls, scene: Scene, given: Mesh, facts: SceneFacts) -> SceneFacts:
        """``facts`` with the one-sample spreads.

        The whole profile's and, where the hybrid's split narrows, its global part's (:attr:`narrowed_spread`).
        """
        mat = _Profile.of(scene.material).module
        eye = scene.camera.eye
        whole = sampling_spread(given, mat, scene.lights, eye)
        facts = dataclasses.replace(facts, sampling_spread=whole, narrowed_spread=whole)
        scale, stride, _, _ = hybrid_split_plan(facts)
        if scale > 1 and stride > 0:  # the near field the narrowed split samples: its global part's spread
            split = _global_part(mat, HybridRenderer.defaults["c"] * scale)
            facts = dataclasses.replace(facts, narrowed_spread=sampling_spread(given, mat, scene.lights, eye,
                                                                               sampled=split))
        return facts

    @classmethod
    def _compute(cls, scene: Scene, mesh: Mesh, throughput: bool, spread: bool = True) -> SceneFacts:
        given = mesh  # decimated as given (its dtype does not change the collapse), so the plan's fit reuses it
        mesh = mesh.with_dtype(torch.float64)
        prof = _Profile.of(scene.material)
        mat = prof.module
        v = mesh.vertices.detach()
        lo, hi = v.amin(0), v.amax(0)
        centre = 0.5 * (lo + hi)
        radius = float((v - centre).norm(dim=1).max())
        f = mesh.faces
        edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        median_edge = float((v[edges[:, 0]] - v[edges[:, 1]]).norm(dim=1).median())
        tm = mesh.to_trimesh()
        hull = tm.convex_hull
        # a scan with a few holes or non-manifold edges (the shared bunny, igea, teapot) still encloses about its
        # divergence-theorem volume (igea: 1135 mm^3 against its hull's 1258): bounded by the hull's, it gives the
        # thickness; only a watertight mesh can be convex
        volume = abs(float(tm.volume))
        if not tm.is_watertight:
            volume = min(volume, abs(float(hull.volume)))
        convex = bool(tm.is_watertight and hull.volume > 0 and volume >= 0.98 * float(hull.volume))
        area = float(mesh.area)
        thickness = 4.0 * volume / area if volume > 0 else 0.0
        cam = scene.camera
        eye = torch.tensor(cam.eye, dtype=torch.float64)
        dist = float((eye - centre).norm())
        per_mm = 2.0 * math.tan(math.radians(cam.fov_deg) / 2.0) / cam.height  # pixel size over distance
        pixel = max(dist - radius, 1e-3) * per_mm  # at the nearest surface: the finest detail a pixel shows
        covered = min(float(hull.area) / 4.0 / (dist * per_mm) ** 2, float(cam.width * cam.height))
        unlit = _unlit(scene, centre, eye)
        sa, ss = mat.sigma_a.detach().double(), mat.sigma_s_prime.detach().double()
        ell = 1.0 / torch.sqrt(3.0 * sa * (sa + ss))
        spacing = reference_spacing(prof, mesh.size_mm, TRUTH_EPS)
        hs = [reference_spacing(prof, mesh.size_mm, e) for e in REFERENCE_EPS]
        sources = tuple(source_count(mesh, h) for h in hs)
        wanted = tuple(min(mesh.num_faces, source_faces(area, h)) for h in hs)
        decimated = tuple(min(n, int(SOURCES_PER_FACE * w)) for n, w in zip(sources, wanted))
        dev = _deviations(mesh, given, [w for w in wanted if w * 2 <= mesh.num_faces])
        deviation = tuple(dev.get(w, 0.0) for w in wanted)
        # splat's truncation on the scene; not under an environment (its light, smooth over the surface, is not in
        # the closed form: the planar tail is charged instead)
        radii = [prof.r_max(e) for e in SPLAT_EPS]
        if any(isinstance(light, EnvironmentLight) for light in scene.lights):
            truncation = ()
        elif min(radii) < 2.0 * radius:
            truncation = truncation_error(given, mat, scene.lights, cam.eye, radii)
        else:
            truncation = tuple(0.0 for _ in radii)
        facts = cls(faces=mesh.num_faces, size_mm=float(mesh.size_mm), area_mm2=area, radius_mm=radius,
                   median_edge_mm=median_edge, convex=convex, thickness_mm=thickness, pixel_mm=pixel,
                   covered_px=covered,
                   pixels=cam.width * cam.height, lights=len(scene.lights), unlit=unlit,
                   ell_mm=tuple(float(x) for x in ell), r_max_mm=prof.r_max_channels(TRUTH_EPS),
                   spacing_mm=spacing, sources=sources, source_faces=wanted, sources_decimated=decimated,
                   throughput_entries=estimate_throughput_entries(mesh, mat, rows=64) if throughput else -1,
                   source_deviation_mm=deviation, local_bound_mm=hybrid_local_bound(mat, radius),
                   irradiance_detail=irradiance_detail(mesh, scene.lights), sampling_spread=-1.0,
                   narrowed_spread=-1.0, light_fill=_light_fill(scene, mesh, float(mat.eta.detach().reshape(-1)[0])),
                   splat_truncation=truncation)
        if throughput:
            # on the mesh Lensch builds on: where the throughput would not fit, decimated as candidates() will
            # (larger vertex areas are cut less: the 30 mm marble bunny's full mesh 0.23-0.48%, where its Lensch
            # build on 5,898 faces measured the same at 1e-5 and 1e-6)
            fit = _lensch_fit(mesh.num_faces, facts.throughput_entries)
            lensch_mesh = _source_mesh(given, max(500, fit)) if fit < 0.95 * mesh.num_faces else mesh
            cut = throughput_cut(lensch_mesh, mat, scene.lights, scene.camera.eye, LENSCH_THRESHOLDS)
            finer = tuple(estimate_throughput_entries(mesh, mat, threshold=t, rows=64) for t in LENSCH_THRESHOLDS[1:]) \
                if cut[0] > CUT_MATTERS else ()
            facts = dataclasses.replace(facts, throughput_cut=cut, throughput_entries_finer=finer)
        # the hybrid's surface local samples: its mesh decimated to the truth's spacing where that saves faces
        # (a 268k-face scan holds 26k samples there, not its 268k; build_hybrid), and the split's narrowing
        local = decimated[0] if wanted[0] < mesh.num_faces else sources[0]
        facts = dataclasses.replace(facts, local_samples=int(local))
        if hybrid_local_plan(facts)[0] < 0:  # only then (each bound's R_p is a bisection: 30 ms)
            narrowed = tuple(hybrid_local_bound(mat, radius, c=HybridRenderer.defaults["c"] * scale)
                             for scale in NARROWING[1:])
            facts = dataclasses.replace(facts, narrowed_bounds_mm=narrowed)
        if spread:
            facts = cls._spreads(scene, given, facts)
        target = detail_faces(facts)
        if target is None:
            return facts
        atlas_dev = dev[target] if target in dev else surface_deviation(mesh, _source_mesh(given, target))
        return dataclasses.replace(facts, atlas_deviation_mm=atlas_dev)


#: SceneFacts.from_scene's cache: (hash of the scene, id of the mesh) -> (mesh, scene, facts).
_FACTS: dict[tuple[int, int], tuple[Mesh, Scene, SceneFacts]] = {}


#: The scales of Chang's importance bound ``c`` the hybrid's renderer tries, in order, until its surface local term's
#: pairs fit (:meth:`~torchsss.pipelines.chang.HybridRenderer`'s local plan: the split narrows).
NARROWING = (1, 2, 4, 8, 16)


def hybrid_local_bound(material: torch.nn.Module, radius_mm: float, *, c: float | None = None) -> float:
    """The hybrid's local bound :math:`r_b = R_p + \\ln(0.5/\\epsilon_l)/k` at its default split (mm), 0 when off.

    As :func:`~torchsss.pipelines.chang.build_hybrid` at :class:`~torchsss.pipelines.chang.HybridRenderer`'s default
    knobs (``c``, ``k``, ``max_reach``: the split off beyond that times the object's radius) and the surface local
    term's ``local_eps`` 1e-2. ``c``: Chang's importance bound instead of the default's (a narrowed split, whose
    weight's tail the renderer shortens to at most :math:`2 R_p`; :meth:`HybridRenderer._split`).
    """
    weight = _split_weight(material, c)
    bound = 0.0 if weight is None else weight.bound
    return 0.0 if bound > HybridRenderer.defaults["max_reach"] * radius_mm else bound


def _split_weight(material: torch.nn.Module, c: float | None = None) -> ChangLocalProfile | None:
    """The local weight :math:`W_l^b` of the hybrid's split at importance bound ``c`` (default: the knob's), or None.

    As the renderer builds it (``HybridRenderer._split``): :math:`R_p` from Chang's bound (the dipole's closed form,
    else the profile's), the blend :math:`k` the knob's at the default ``c`` and, narrowed, at least
    :math:`\\ln(0.5/\\epsilon_l) / (2 R_p)` (the tail at most :math:`2 R_p` past :math:`R_p`), truncated where
    :math:`W_l = \\epsilon_l` (1e-2, the surface local term's). None where :math:`R_p = 0` (no split).
    """
    knobs = HybridRenderer.defaults
    default = c is None or float(c) == knobs["c"]
    c = knobs["c"] if c is None else float(c)
    local_eps = 1e-2 if knobs["local_eps"] is None else knobs["local_eps"]
    with torch.no_grad():
        if all(hasattr(material, a) for a in ("sigma_a", "sigma_s_prime", "eta")):
            r_p = float(chang_rp(material.sigma_a.detach(), material.sigma_s_prime.detach(), material.eta.detach(),
                                 c=c).amax())
        else:
            r_p = profile_rp(material, c)
    if r_p <= 0:
        return None
    tail = math.log(0.5 / local_eps)
    k = knobs["k"] if default else max(knobs["k"], tail / (2.0 * r_p))
    return ChangLocalProfile(r_p, k, r_p + tail / k)


def _global_part(material: torch.nn.Module, c: float) -> SplitProfile:
    """The global part :math:`R_d (1 - W_l^b)` of the hybrid's split at importance bound ``c`` (a profile)."""
    return SplitProfile(material, _split_weight(material, c), "global")


def _local_fit(facts: SceneFacts, bound: float, m: dict) -> tuple[int, float, float]:
    """``(stride, pairs, per)`` of the surface local term at local bound ``bound`` (stride -1: nothing fits)."""
    px = facts.covered_px
    samples = facts.local_samples or facts.sources[0]
    per = samples * min(1.0, math.pi * bound ** 2 / max(facts.area_mm2, 1e-9))
    budget = HybridRenderer.defaults["max_local_pairs"] / m["hybrid_local_headroom"]
    for stride in LOCAL_STRIDES:
        receivers = px if stride == 1 else px / stride ** 2 + m["hybrid_local_edge"] * math.sqrt(px)
        if receivers * per <= budget:
            return stride, receivers * per, per
    return -1, 0.0, per


def hybrid_split_plan(facts: SceneFacts, model: dict | None = None) -> tuple[int, int, float, float]:
    """The split the hybrid's renderer is predicted to take: ``(scale, stride, pairs, per)``.

    ``scale``: Chang's importance bound is the default's times this (:data:`NARROWING`: 1 where the default split's
    local pairs fit, :func:`hybrid_local_plan`; else the first narrowed split whose pairs fit at some stride, as the
    renderer tries them); 0 with ``stride`` 0 where there is no split (off, or narrowed away: everything sampled);
    the last scale with ``stride`` -1 where even the narrowest does not fit (the renderer then takes the atlas
    filter).
    """
    m = {**MODEL, **(model or {})}
    if facts.local_bound_mm <= 0:
        return 0, 0, 0.0, 0.0
    stride, pairs, per = hybrid_local_plan(facts, m)
    if stride > 0:
        return 1, stride, pairs, per
    for scale, bound in zip(NARROWING[1:], facts.narrowed_bounds_mm):
        if bound <= 0:
            return 0, 0, 0.0, 0.0
        stride, pairs, per = _local_fit(facts, bound, m)
        if stride > 0:
            return scale, stride, pairs, per
    return NARROWING[-1], -1, 0.0, per


def hybrid_local_plan(facts: SceneFacts, model: dict | None = None) -> tuple[int, float, float]:
    """The hybrid's surface local term on a scene, predicted: ``(stride, pairs, pairs per receiver)``.

    Stride 0: no split (nothing local); -1: the pairs do not fit even at stride 8 and the renderer narrows the split
    (:func:`hybrid_split_plan`: more of the near field sampled, noisier than the hybrid's error model, which is fitted
    on unnarrowed splits). A receiver gathers the hybrid's surface samples (:attr:`SceneFacts.local_samples`: the
    mesh decimated to the truth's spacing; the full mesh's :attr:`SceneFacts.sources` where that is not set) on the
    part of the surface within
    :math:`r_b`, about :math:`n\\,\\pi r_b^2 / A`; at stride ``s`` the renderer evaluates about
    :math:`P/s^2 + e\\sqrt{P}` receivers of the :math:`P` covered pixels, the second term the gaps and silhouettes it
    evaluates exactly (``hybrid_local_edge``: 14.6, from the side-lit 30 mm marble torus at 128 x 128, a calibration
    scene: the renderer listed 5.46M pairs at stride 2, about 1,500 receivers at this estimate's 3,600 pairs each,
    where the planner counts 2,910 covered pixels). The renderer's own count decides; this estimate is taken with a
    headroom of ``hybrid_local_headroom`` (2, set after the 50 mm marble bunny at 256 x 256 narrowed where the
    estimate without it fitted) before a stride is predicted to fit.
    """
    m = {**MODEL, **(model or {})}
    if facts.local_bound_mm <= 0:
        return 0, 0.0, 0.0
    return _local_fit(facts, facts.local_bound_mm, m)


def _light_fill(scene: Scene, mesh: Mesh, eta: float) -> float:
    """:attr:`SceneFacts.light_fill`: splat's sources of each light at a :data:`FILL_GRID` light view, per texel."""
    fills = [light_sources(mesh, light, FILL_GRID, eta, 0, coverage=False, flux="facet")[0].shape[0]
             / FILL_GRID ** 2 for light in scene.lights if isinstance(light, (PointLight, SpotLight, DirectionalLight))]
    return sum(fills) / len(fills) if fills else 0.5


def _unlit(scene: Scene, centre: torch.Tensor, eye: torch.Tensor) -> float:
    """:attr:`SceneFacts.unlit` (environment lights count as front light)."""
    view = (eye - centre) / (eye - centre).norm()
    num = den = 0.0
    for light in scene.lights:
        if hasattr(light, "position"):
            d = torch.tensor(light.position, dtype=torch.float64) - centre
            dist2 = float(d.square().sum())
            w = float(sum(light.intensity)) / max(dist2, 1e-12)
            d = d / math.sqrt(max(dist2, 1e-24))
        elif hasattr(light, "direction"):
            d = -torch.tensor(light.direction, dtype=torch.float64)
            d = d / d.norm()
            w = float(sum(light.irradiance))
        else:
            continue
        num += w * (1.0 - float(d @ view)) / 2.0
        den += w
    return num / den if den > 0 else 0.0


def _face_irradiance(v: torch.Tensor, f: torch.Tensor, lights: Sequence):
    """Per face: area, unit normal, centroid and the unshadowed irradiance per channel at the centroid.

    ``v`` :math:`(V, 3)` float64 vertices (mm), ``f`` :math:`(F, 3)` faces -> area :math:`(F,)`, normal and
    centroid :math:`(F, 3)`, irradiance through the face's normal :math:`(F, 3)` (point, spot and directional
    lights; environments are smooth over the surface and skipped).
    """
    tri = v[f]
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    area = 0.5 * cross.norm(dim=-1)
    normal = cross / (2.0 * area.clamp_min(1e-300)).unsqueeze(-1)
    centroid = tri.mean(dim=1)
    e = torch.zeros(f.shape[0], 3, dtype=v.dtype, device=v.device)
    for light in lights:
        try:
            to_light, _, e_perp = incident_light(light, centroid.unsqueeze(0))
        except TypeError:  # an environment: smooth over the surface
            continue
        e = e + (normal * to_light[0]).sum(-1, keepdim=True).clamp_min(0.0) * e_perp[0]
    return area, normal, centroid, e


def irradiance_detail(mesh: Mesh, lights: Sequence) -> float:
    """The direct irradiance's relative detail where creases meet, at the scale of the vertex hats, in [0, 1].

    Per face :math:`E_f`, the unshadowed irradiance at its centroid through its own normal (summed over the
    point, spot and directional lights and their channels; environments are smooth and add none); per vertex
    :math:`E_v` the area-weighted mean of its faces'; :math:`\\tilde E_f` the mean of its corners' :math:`E_v` (what a
    function carried by the vertex hats sees). Over the faces beside a crease (an edge whose faces turn by more than
    :data:`~torchsss.geometry.mesh.CREASE_DEG`), where a chart seam parts the surface, the result is
    :math:`\\sqrt{\\sum_{f \\in C} A_f (E_f - \\tilde E_f)^2 / \\sum_f A_f E_f^2}`: 0 on a mesh without creases, 0.58
    on a 25 mm slab lit at 5.5 degrees to its face (its 1.25 mm rim takes ten times the face's irradiance), 0.14 on a
    front-lit one, 0.001-0.04 on the teapot, spot and the scans. Over all faces the same measure is 5-12% on smooth
    scans (their terminators), where Lensch measures 0.2-2.9%: within a chart the kernels answer that detail. Cast
    shadows are not counted. Lensch now parts its hats at creases (:func:`~torchsss.geometry.mesh.split_creases`), so
    the jump itself is carried; the measure stays the proxy of what is left, the radiosity beside the crease, which
    varies within one hat: charged as it is, it is conservative (the rim-lit slab at 128 x 128: 18.8% measured
    before, 3.06% at 256 x 256 since the renderer grades rows of vertices towards the creases, ``refine_mm``, and
    reads their radiosity at each pixel; not yet modelled here).

    Examples:
        >>> from torchsss.geometry import DirectionalLight, sphere
        >>> irradiance_detail(sphere(10.0, 4), [DirectionalLight((0, 0, -1), 1.0)])
        0.0
    """
    v = mesh.vertices.detach().double()
    f = mesh.faces
    area, normal, _, e = _face_irradiance(v, f, lights)
    e = e.sum(-1)
    total = float((area * e * e).sum())
    if total <= 0.0:
        return 0.0
    num = torch.zeros(v.shape[0], dtype=torch.float64, device=v.device).index_add(0, f.reshape(-1),
                                                                                  (area * e).repeat_interleave(3))
    den = torch.zeros(v.shape[0], dtype=torch.float64, device=v.device).index_add(0, f.reshape(-1),
                                                                                  area.repeat_interleave(3))
    ev = num / den.clamp_min(1e-300)
    smooth = ev[f].mean(dim=1)
    # only where a crease's faces meet: elsewhere the detail stays within a chart and the kernels answer it
    a, b = f.roll(-1, dims=1).reshape(-1), f.roll(-2, dims=1).reshape(-1)
    key = torch.minimum(a, b) * v.shape[0] + torch.maximum(a, b)
    order = torch.argsort(key, stable=True)
    same = key[order][1:] == key[order][:-1]
    fa, fb = order[:-1][same] // 3, order[1:][same] // 3
    crease = (normal[fa] * normal[fb]).sum(-1) < math.cos(math.radians(CREASE_DEG))
    near = torch.zeros(f.shape[0], dtype=torch.bool, device=v.device)
    near[fa[crease]] = True
    near[fb[crease]] = True
    return math.sqrt(float((area * (e - smooth) ** 2 * near).sum()) / total)


#: The faces :func:`sampling_spread` works on (a larger mesh is decimated to this many; about 0.1-0.5 s a scene).
SPREAD_FACES = 3000
#: The receivers :func:`sampling_spread` averages over (a random subset of the faces the camera faces, seeded).
SPREAD_RECEIVERS = 1500
#: The receivers :func:`truncation_error` averages over (its mean share needs fewer than the spread's variance).
TRUNCATION_RECEIVERS = 500


def _disk_moments(profile, radius: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The profile and its square integrated over disks of ``radius`` :math:`(F,)` mm: :math:`(F, C)` each.

    Gauss-Legendre on radial intervals graded by 4 towards the centre (the profile's peak at 0 resolved).
    """
    x, w = np.polynomial.legendre.leggauss(8)
    edges = [0.0] + [4.0 ** -k for k in range(5, -1, -1)]
    t = torch.tensor(np.concatenate([lo + 0.5 * (x + 1.0) * (hi - lo) for lo, hi in itertools.pairwise(edges)]),
                     dtype=radius.dtype, device=radius.device)
    wt = torch.tensor(np.concatenate([0.5 * w * (hi - lo) for lo, hi in itertools.pairwise(edges)]),
                      dtype=radius.dtype, device=radius.device)
    r = radius[:, None] * t[None, :]
    rd = profile(r.unsqueeze(-1))  # (F, q, C)
    jac = (2.0 * math.pi * r * radius[:, None] * wt[None, :]).unsqueeze(-1)
    return (rd * jac).sum(1), (rd.square() * jac).sum(1)


class _Seen(NamedTuple):
    """The faces :func:`sampling_spread` and :func:`truncation_error` work on (:func:`_seen_faces`)."""

    vertices: torch.Tensor  # (V, 3) mm, float64
    area: torch.Tensor  # (F,) mm^2
    centroid: torch.Tensor  # (F, 3) mm
    irradiance: torch.Tensor  # (F, C) unshadowed, through each face's normal
    receivers: torch.Tensor  # (R,) faces the camera faces (at most _seen_faces' receivers, seeded)
    sources: torch.Tensor  # (S,) lit faces
    weight: torch.Tensor  # (R,) each receiver's solid angle seen from the eye
    flux: torch.Tensor  # (S, C) each source's irradiance times its area


def _seen_faces(mesh: Mesh, lights: Sequence, eye: Sequence[float], receivers: int = SPREAD_RECEIVERS) -> _Seen | None:
    """The lit faces and the faces the camera faces, on ``mesh`` decimated to :data:`SPREAD_FACES`.

    At most ``receivers`` of the faces the camera faces (a seeded choice). None if either is empty. Raises
    ValueError for an ``eye`` that is not three finite numbers.
    """
    try:
        eye = [float(x) for x in eye]
    except (TypeError, ValueError):
        eye = None
    if eye is None or len(eye) != 3 or not all(math.isfinite(x) for x in eye):
        raise ValueError("eye: expected the camera's position as three finite numbers (mm)")
    m = mesh.with_dtype(torch.float64)
    if m.num_faces > SPREAD_FACES:
        m = _source_mesh(mesh, SPREAD_FACES, ladder=True).with_dtype(torch.float64)
    v, f = m.vertices.detach(), m.faces
    area, normal, centroid, e = _face_irradiance(v, f, lights)
    view = torch.tensor(eye, dtype=torch.float64, device=v.device) - centroid
    dist = view.norm(dim=-1).clamp_min(1e-9)
    cos = (normal * view).sum(-1) / dist
    recv = (cos > 0).nonzero()[:, 0]
    src = (e.sum(-1) > 0).nonzero()[:, 0]
    if recv.numel() == 0 or src.numel() == 0:
        return None
    if recv.numel() > receivers:
        pick = torch.randperm(recv.numel(), generator=torch.Generator().manual_seed(0))[:receivers]
        recv = recv[pick.to(recv.device)]
    w = area[recv] * cos[recv] / dist[recv].square()
    return _Seen(v, area, centroid, e, recv, src, w, e[src] * area[src, None])


def _fast_profile(profile, v: torch.Tensor):
    """The pairs' profile in float32 from a table of it, over the extent of the vertices ``v``.

    :func:`bulk_profile` is 2-6x faster than the formula, within 2e-5; float32 pairs are 2x faster than float64,
    within 1e-5.
    """
    single = copy.deepcopy(profile).float() if isinstance(profile, torch.nn.Module) else profile
    return bulk_profile(single, float((v.amax(0) - v.amin(0)).norm()) + 1e-6, torch.float32, v.device)


def _pair_blocks(seen: _Seen, fast):
    """The (receiver, source) pairs of ``seen`` in blocks of receivers (about 2M pairs each), outside autograd.

    Yields ``(block, d, rd, own)``: the receivers' slice, their distances to every source :math:`(r, S, 1)` mm in
    float32, the profile ``fast`` there :math:`(r, S, C)` with each receiver's own face's pair set to 0 (a disk of
    its area stands for it, :func:`_disk_moments`), and that pair's ``(rows, cols)``.
    """
    v, _, centroid, _, recv, src, _, _ = seen
    c32 = centroid.float()
    at = torch.full((centroid.shape[0],), -1, dtype=torch.long, device=v.device)
    at[src] = torch.arange(src.numel(), device=v.device)
    step = max(1, 2_000_000 // max(src.numel(), 1))
    for lo in range(0, recv.numel(), step):
        r = recv[lo:lo + step]
        d = torch.cdist(c32[r], c32[src], compute_mode="donot_use_mm_for_euclid_dist").unsqueeze(-1)
        own_row = (at[r] >= 0).nonzero()[:, 0]
        own = (own_row, at[r][own_row])
        rd = fast(d)
        rd[own] = 0.0
        yield slice(lo, lo + step), d, rd, own


def truncation_error(mesh: Mesh, profile, lights: Sequence, eye: Sequence[float], radii: Sequence[float], *,
                     receivers: int = TRUNCATION_RECEIVERS) -> tuple[float, ...]:
    r"""The relative RMS of the seen radiosity that reaches each receiver from beyond each of ``radii`` (mm).

    What a renderer that cuts the profile at a radius :math:`r` (splatting at :math:`r_{max}(\epsilon)`, the same
    radius for every channel) drops: per receiver :math:`x` and channel, :math:`T_r(x) = \int_{|x - s| > r}
    R_d(|x - s|) E(s)\,ds` against :math:`L(x) = \int R_d E\,ds`, and :math:`\sqrt{\sum_x w_x \sum_c T^2 /
    \sum_x w_x \sum_c L^2}` over the faces the camera faces, weighted by their solid angle, as
    :func:`sampling_spread` (closed form on the faces of the mesh decimated to :data:`SPREAD_FACES`, unshadowed
    irradiance at the centroids, a receiver's own face as a disk of its area; 3-D distances, so light that crossed
    a thick object counts as far; within two face spacings the surface is taken as the receiver's plane, lit as the
    receiver). The planar tail :func:`~torchsss.physics.profile_tail_fraction` bounds it on a
    wide flat object; on a curved or back-lit one it can be far smaller or larger (the default scene at
    :math:`\epsilon` = 0.003: 0.25% where the planar tail to the object's diameter says 2.8%).

    Args:
        mesh: The object (mm).
        profile: Its material: distances :math:`(..., 1)` mm -> :math:`R_d` :math:`(..., C)`.
        lights: The scene's lights (environments are ignored).
        eye: The camera's position (mm).
        radii: The truncation radii (mm).
        receivers: At most this many receivers (a seeded choice of the faces the camera faces).

    Returns:
        One relative error per radius (0 where no light is seen).

    Raises:
        TypeError: ``mesh`` not a Mesh, ``profile`` not callable.
        ValueError: ``eye`` not three finite numbers, a negative or non-finite radius.

    Examples:
        >>> from torchsss.geometry import DirectionalLight, sphere
        >>> from torchsss.modules import DipoleMaterial
        >>> near, far = truncation_error(sphere(10.0, 3), DipoleMaterial.from_preset("skin1"),
        ...                              [DirectionalLight((0, 0, -1), 1.0)], (0.0, 0.0, 40.0), (1.0, 30.0))
        >>> 0.0 < near < 1.0 and far == 0.0
        True
    """
    mesh = check_mesh(mesh)
    if not callable(profile):
        raise TypeError(f"profile: expected a callable profile (distances -> R_d), got {type(profile).__name__}")
    try:
        radii = [float(r) for r in radii]
    except (TypeError, ValueError):
        raise ValueError(f"radii: expected a sequence of radii in mm, got {radii!r}") from None
    if not all(math.isfinite(r) and r >= 0.0 for r in radii):
        raise ValueError(f"radii: expected finite radii >= 0 mm, got {radii}")
    seen = _seen_faces(mesh, lights, eye, receivers)
    if seen is None:
        return tuple(0.0 for _ in radii)
    v, area, _, e, recv, _, w, flux = seen
    with torch.no_grad():
        flux32 = flux.float()
        lum = torch.zeros(recv.numel(), flux.shape[1], dtype=torch.float64, device=v.device)
        far = torch.zeros(len(radii), *lum.shape, dtype=torch.float64, device=v.device)
        # faces as points are a fair quadrature beyond two face spacings; a radius inside that is met in the plane
        # (the receiver's own irradiance over the annulus from the radius to two spacings, a disk difference)
        near = 2.0 * math.sqrt(float(area.mean()))
        cuts = [max(radius, near) for radius in radii]
        for block, d, rd, _ in _pair_blocks(seen, _fast_profile(profile, v)):
            lum[block] = torch.einsum("rsc,sc->rc", rd, flux32).double()
            for k, radius in enumerate(cuts):
                far[k, block] = torch.einsum("rsc,sc->rc", rd * (d > radius).float(), flux32).double()
        profile64 = lambda x: profile(x).double()  # noqa: E731
        own, _ = _disk_moments(profile64, (area[recv] / math.pi).sqrt())
        ones = torch.ones(1, dtype=torch.float64, device=v.device)
        for k, radius in enumerate(radii):
            if radius < near:
                ring = _disk_moments(profile64, near * ones)[0] - _disk_moments(profile64, radius * ones)[0]
                far[k] += e[recv] * ring
    lum = lum + e[recv] * own
    den = float((w[:, None] * lum.square()).sum())
    if den <= 0.0:
        return tuple(0.0 for _ in radii)
    return tuple(math.sqrt(float((w[:, None] * far[k].square()).sum()) / den) for k in range(len(radii)))


def sampling_spread(mesh: Mesh, profile, lights: Sequence, eye: Sequence[float], *, sampled=None) -> float:
    """The relative standard deviation of one irradiance-importance sample of the seen radiosity.

    The icdf estimator draws sources with probability :math:`p(s) \\propto E(s)\\,dA` and averages
    :math:`\\Phi R_d(|x - s|)` (:math:`\\Phi = \\int E\\,dA`, per channel). One sample's variance at a receiver
    :math:`x` is :math:`\\Phi \\int R_d(|x - s|)^2 E(s)\\,ds - L(x)^2` with :math:`L(x) = \\int R_d E\\,ds`; this
    returns :math:`\\sqrt{\\sum_x w_x \\sum_c \\mathrm{Var}_c(x) / \\sum_x w_x \\sum_c L_c(x)^2}` over the faces
    the camera faces, weighted by their solid angle :math:`w_x` (the pixels they cover). Large where the light
    enters a small area near what the camera sees (a slab lit on its rim: 13), small where it spreads over a
    surface the profile averages (a back-lit ketchup bunny: 0.9). Computed in closed form on the faces (mesh
    decimated to :data:`SPREAD_FACES`): the unshadowed irradiance at each centroid through its face's normal,
    source faces at their centroids, a receiver's own face as a disk of its area
    (:func:`_disk_moments`), at most :data:`SPREAD_RECEIVERS` receivers. Environment lights are ignored (smooth
    over the surface); without any other light the result is 1.

    With ``sampled``, the estimator samples that part :math:`g` of the profile only (the hybrid's global part
    :math:`R_d (1 - W_l^b)`, the rest being computed exactly): the variance is that of :math:`\\Phi g`, relative
    to the whole radiosity :math:`L = \\int R_d E\\,ds` still.

    Args:
        mesh: the object (mm).
        profile: the material's profile, distances :math:`(..., 1)` mm -> :math:`R_d` :math:`(..., C)` mm^-2.
        lights: the scene's lights.
        eye: the camera's position (mm).
        sampled: the sampled part of ``profile`` (same signature), or None (all of it).

    Returns:
        The relative standard deviation of one sample (>= 0).

    Raises:
        TypeError: ``mesh`` not a Mesh, ``profile`` not callable.
        ValueError: ``eye`` not three finite numbers.

    Examples:
        >>> from torchsss.geometry import DirectionalLight, sphere
        >>> from torchsss.modules import DipoleMaterial
        >>> q = sampling_spread(sphere(10.0, 3), DipoleMaterial.from_preset("skin1"),
        ...                     [DirectionalLight((0, 0, -1), 1.0)], (0.0, 0.0, 40.0))
        >>> 1.0 < q < 20.0
        True
    """
    mesh = check_mesh(mesh)
    if not callable(profile):
        raise TypeError(f"profile: expected a callable profile (distances -> R_d), got {type(profile).__name__}")
    if sampled is not None and not callable(sampled):
        raise TypeError(f"sampled: expected a callable profile part or None, got {type(sampled).__name__}")
    seen = _seen_faces(mesh, lights, eye)
    if seen is None:
        return 1.0
    v, area, _, e, recv, _, w, flux = seen
    with torch.no_grad():
        flux32 = flux.float()
        out_l = torch.zeros(recv.numel(), flux.shape[1], dtype=torch.float64, device=v.device)
        out_s = torch.zeros_like(out_l)
        out_g = torch.zeros_like(out_l) if sampled is not None else out_l
        for block, d, rd, own in _pair_blocks(seen, _fast_profile(profile, v)):
            out_l[block] = torch.einsum("rsc,sc->rc", rd, flux32).double()
            if isinstance(sampled, SplitProfile) and sampled.material is profile:
                # a split of this profile (the hybrid's global part): the table's profile times the split's weight
                w_l = sampled.weight(d)
                rd = rd * (w_l if sampled.part == "local" else 1.0 - w_l)
                out_g[block] = torch.einsum("rsc,sc->rc", rd, flux32).double()
            elif sampled is not None:
                rd = sampled(d.double()).float()
                rd[own] = 0.0
                out_g[block] = torch.einsum("rsc,sc->rc", rd, flux32).double()
            out_s[block] = torch.einsum("rsc,sc->rc", rd.square_(), flux32).double()
        radius = (area[recv] / math.pi).sqrt()
        d1, d2 = _disk_moments(lambda x: profile(x).double(), radius)
        g1, g2 = (d1, d2) if sampled is None else _disk_moments(lambda x: sampled(x).double(), radius)
    lum = out_l + e[recv] * d1
    part = lum if sampled is None else out_g + e[recv] * g1
    sq = out_s + e[recv] * g2
    var = (flux.sum(0)[None, :] * sq - part.square()).clamp_min(0.0)
    den = float((w[:, None] * lum.square()).sum())
    return math.sqrt(float((w[:, None] * var).sum()) / den) if den > 0 else 1.0


def source_faces(area_mm2: float, spacing_mm: float) -> int:
    """Faces that carry the reference's sources at ``spacing_mm``: ``faces_for_spacing`` of the geometry layer."""
    return faces_for_spacing(area_mm2, spacing_mm)


def reference_spacing(profile: _Profile, size_mm: float, eps: float) -> float:
    """The reference's default sample spacing at ``eps`` (:func:`~torchsss.pipelines.reference.default_spacing`)."""
    return max(profile.spacing(eps), float(size_mm) / 4000.0)


def source_count(mesh: Mesh, spacing_mm: float) -> int:
    """The reference's sample count at ``spacing_mm`` (:func:`~torchsss.geometry.sampling.surface_samples`)."""
    tri = mesh.triangles().detach().double()
    longest = torch.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], 1).norm(dim=-1)
    n = torch.ceil(longest.amax(1) / spacing_mm).clamp_min(1.0)
    return int((n * n).sum())


@dataclass
class Plan:
    """A planned render: what to run and why.

    Attributes:
        method: the method to build.
        knobs: its knobs (pass to :func:`torchsss.pipelines.build` / ``render_scene``).
        decimate: the mesh's decimation target (faces), or None for the full mesh.
        modelled: the terms the plan models.
        skipped: the terms it skips (each with the reason in ``reasons``).
        predicted_error: predicted relative RMSE against the reference.
        predicted_setup_s: predicted setup time.
        predicted_frame_s: predicted time of one frame.
        tolerance: the asked tolerance.
        frames: the frames the cost was planned for.
        reasons: one line per choice (method, each knob, each rule that applied).
        facts: the :class:`SceneFacts` as a dict.
        candidates: every candidate considered, with its predictions (cheapest first).
    """

    method: str
    knobs: dict
    decimate: int | None
    modelled: list[str]
    skipped: list[str]
    predicted_error: float
    predicted_setup_s: float
    predicted_frame_s: float
    tolerance: float
    frames: int
    reasons: dict[str, str] = field(default_factory=dict)
    facts: dict = field(default_factory=dict)
    candidates: list[dict] = field(default_factory=list)

    @property
    def predicted_total_s(self) -> float:
        """Setup plus ``frames`` frames."""
        return self.predicted_setup_s + self.frames * self.predicted_frame_s

    def scene(self, scene: Scene) -> Scene:
        """``scene`` with the plan's decimation applied."""
        return dataclasses.replace(scene, decimate=self.decimate) if self.decimate else scene

    def to_json(self) -> dict:
        """The plan as JSON values."""
        d = dataclasses.asdict(self)
        d["predicted_total_s"] = self.predicted_total_s
        return d

    def __str__(self) -> str:
        lines = [f"plan: {self.method} {json.dumps(self.knobs)}"
                 + (f", mesh decimated to {self.decimate} faces" if self.decimate else ""),
                 f"  predicted error {self.predicted_error:.2%} (tolerance {self.tolerance:.2%}), setup "
                 f"{self.predicted_setup_s:.2f} s, frame {self.predicted_frame_s:.2f} s, {self.frames} frame(s): "
                 f"{self.predicted_total_s:.2f} s",
                 f"  modelled: {', '.join(self.modelled)}",
                 f"  skipped: {', '.join(self.skipped) or 'nothing'}"]
        lines += [f"  {k}: {v}" for k, v in self.reasons.items()]
        return "\n".join(lines)


class _Profile:
    """A material's spacing, r_max and alias error, memoised (each bisection costs 0.1-0.4 s)."""

    _cache: ClassVar[dict[tuple, _Profile]] = {}

    def __init__(self, material) -> None:
        self.module = material_module(material, dtype=torch.float64)
        self.mt = tuple(t.detach().double() for t in (self.module.sigma_a, self.module.sigma_s_prime,
                                                      self.module.eta))
        self._memo: dict[tuple, float] = {}

    @classmethod
    def of(cls, material) -> _Profile:
        if isinstance(material, Material) and material.profile != "dipole":
            # the planner's closed forms are the dipole's; another profile of the same coefficients is planned
            # as its dipole (the profiles agree to within their own model error: tests/test_lut_burley.py)
            material = material.with_profile("dipole")
        mod = material_module(material, dtype=torch.float64)
        key = (type(mod).__name__, *(tuple(t.detach().double().reshape(-1).tolist())
                                     for t in (mod.sigma_a, mod.sigma_s_prime, mod.eta)))
        if key not in cls._cache:
            cls._cache[key] = cls(material)
        return cls._cache[key]

    def _get(self, key: tuple, fn) -> float:
        if key not in self._memo:
            self._memo[key] = float(fn())
        return self._memo[key]

    def spacing(self, eps: float) -> float:
        if ("spacing", eps) not in self._memo:  # every eps the planner asks for, in one bisection
            values = sorted({*REFERENCE_EPS, *SPLAT_EPS, TRUTH_EPS, float(eps)})
            for e, h in zip(values, splat_spacing(*self.mt, eps=values)):
                self._memo.setdefault(("spacing", e), float(h.min()))
                self._memo.setdefault(("spacings", e), tuple(float(x) for x in h.reshape(-1)))
        return self._memo[("spacing", eps)]

    def alias_share(self, eps: float) -> float:
        """How much of a lattice's aliasing at the finest channel's spacing the image sees, in (0, 1].

        A light view sampled at the finest channel's spacing :math:`h_{min}` is finer than a channel of spacing
        :math:`h_c` needs by :math:`h_c / h_{min}`, and its aliasing falls as the squared texels per spacing. The
        image's relative error weighs each channel by its brightness (the total diffuse reflectance
        :math:`R_c`): :math:`\\sqrt{\\sum_c w_c (h_{min}/h_c)^4}` with :math:`w_c = R_c^2 / \\sum R^2`. 1 for a
        grey material; ketchup, whose light is red and whose finest spacing is blue's, 0.03 (chicken and skin1
        about 0.36, marble 0.77).
        """
        def share() -> float:
            self.spacing(eps)
            hs = torch.tensor(self._memo[("spacings", eps)], dtype=torch.float64)
            r = total_diffuse_reflectance(*self.mt).reshape(-1).expand_as(hs)
            w = r.square() / r.square().sum().clamp_min(1e-30)
            return float((w * (hs.min() / hs) ** 4).sum().sqrt())

        return self._get(("alias_share", eps), share)

    def r_max(self, eps: float) -> float:
        return self._get(("r_max", eps), lambda: self.module.r_max(eps).max())

    def r_max_channels(self, eps: float) -> tuple[float, ...]:
        return tuple(float(x) for x in self.module.r_max(eps))

    def tail_between(self, r_max: float, diameter: float) -> float:
        """The largest channel's share of the profile's energy between ``r_max`` and ``diameter`` (mm), >= 0.

        :func:`~torchsss.physics.profile_tail_fraction` at both radii: what truncating the profile at ``r_max``
        (one radius for all channels, as the splat renderer does) drops on an object no wider than ``diameter``.
        """
        if r_max >= diameter:
            return 0.0
        key = ("tail", float(f"{r_max:.6g}"), float(f"{diameter:.6g}"))
        return self._get(key, lambda: (profile_tail_fraction(torch.tensor(r_max, dtype=torch.float64), *self.mt)
                                       - profile_tail_fraction(torch.tensor(diameter, dtype=torch.float64),
                                                               *self.mt)).clamp_min(0.0).max())

    def alias(self, h: float) -> float:
        """The RMS over channels of the lattice alias error at spacing ``h`` (mm)."""
        h = float(f"{h:.4g}")
        return self._get(("alias", h), lambda: splat_alias_error(torch.tensor(h, dtype=torch.float64),
                                                                  *self.mt).square().mean().sqrt())


def depth(facts: SceneFacts) -> float:
    """:math:`1 + u \\, t \\, \\sigma_{tr,min}`: how deep the light that the camera sees has travelled.

    The object's mean thickness :math:`t = 4V/S` in scattering lengths of its most penetrating channel, weighted by
    how much of the view faces away from the light (``unlit`` u). Large for a thick back-lit object, whose visible
    light crossed it (the far field that truncation and sampling miss).
    """
    return 1.0 + max(facts.unlit, 0.1) * facts.thickness_mm / max(facts.ell_mm)


def sampling_terms(facts: SceneFacts, fit: str, model: dict | None = None, *,
                   spread: float | None = None) -> tuple[float, float, float]:
    """The Monte Carlo error model of ``fit`` (``"icdf"`` or ``"hybrid"``) on a scene: ``(floor, a, p)``.

    The predicted relative RMSE at :math:`N` samples is :math:`\\sqrt{f^2 + (a (4096/N)^p)^2}` (before the atlas's
    decimation, which :func:`predict` adds). :math:`a` is the fitted ``{fit}_a`` times :math:`u^{\\gamma}
    d^{\\delta}` (``unlit`` u, :func:`depth` d) and, for icdf, :math:`q^{\\beta}` with q the scene's one-sample
    spread (:attr:`SceneFacts.sampling_spread`); the floor is ``{fit}_floor`` (the hybrid's times
    :math:`u^{u\\_floor}`). The exponents are fitted (``benchmarks/fit_planner.py``). The hybrid without a split is
    the icdf estimator: ``fit="icdf"`` (see :func:`hybrid_error`). ``spread``: the icdf's one-sample spread instead
    of the scene's (a narrowed split's global part, :attr:`SceneFacts.narrowed_spread`).
    """
    m = MODEL if model is None else model
    u, d = max(facts.unlit, 0.1), depth(facts)
    a = m[f"{fit}_a"] * u ** m[f"{fit}_u"] * d ** m[f"{fit}_q_depth"]
    if fit == "icdf":
        a *= max(facts.sampling_spread if spread is None else spread, 0.1) ** m["icdf_q_spread"]
    return m[f"{fit}_floor"] * u ** m.get(f"{fit}_u_floor", 0.0), a, m[f"{fit}_p"]


def icdf_error(facts: SceneFacts, samples: int, model: dict | None = None, *, spread: float | None = None) -> float:
    """The icdf estimator's predicted relative RMSE at ``samples`` sources (:func:`sampling_terms`)."""
    floor, a, p = sampling_terms(facts, "icdf", model, spread=spread)
    return math.hypot(floor, a * (4096.0 / samples) ** p)


def hybrid_terms(facts: SceneFacts, model: dict | None = None) -> list[tuple[float, float, float]]:
    """The hybrid's error terms ``[(floor, a, p), ...]``: its predicted error at N is the largest of theirs.

    Where the default split holds (:func:`hybrid_split_plan`), its own fitted model; without a split (off, narrowed
    away) or where nothing fits, the icdf estimator's (the teapot in ketchup without a split, at 3%: N 1024 planned
    on the hybrid's own model at 1.88%, measured 3.63%). Where the split narrows, the near field it gives up is
    sampled: the larger of its own model and the icdf estimator's with the narrowed split's one-sample spread
    (:attr:`SceneFacts.narrowed_spread`; not fitted). The icdf model alone had been used there, with the whole
    profile's spread: the back-lit 50 mm marble example bunny at 256 x 256 (narrowed to c = 0.2) was planned N
    131,072 for 3% and measured 0.45%; the two calibration scenes that narrow (the cream slab and spot) measured
    0.3-0.8% where it predicted 3.4-30%.
    """
    scale, stride, _, _ = hybrid_split_plan(facts, model)
    if stride <= 0:
        return [sampling_terms(facts, "icdf", model)]
    terms = [sampling_terms(facts, "hybrid", model)]
    if scale > 1:
        terms.append(sampling_terms(facts, "icdf", model, spread=facts.narrowed_spread))
    return terms


def hybrid_error(facts: SceneFacts, samples: int, model: dict | None = None) -> float:
    """The hybrid's predicted relative RMSE at ``samples`` (:func:`hybrid_terms`; before the atlas's decimation)."""
    return max(math.hypot(f, a * (4096.0 / samples) ** p) for f, a, p in hybrid_terms(facts, model))


def detail_faces(facts: SceneFacts) -> int | None:
    """The face count that shows the detail the image and the material can show, or None (keep the mesh).

    Target edge: the larger of the pixel footprint and half the shortest scattering length, but at most
    :data:`MAX_EDGE_PX` pixel footprints (the atlas methods render the decimated mesh: its silhouette and shading
    must hold at the image's resolution, whatever the material blurs; a 50 mm marble bunny at 256x256 decimated to
    the 2,000 faces that marble's scattering length allows measured 20-25% error, all at silhouettes and facets);
    faces of an equilateral tessellation of the area at that edge, at least 2000. None when that would not halve
    the mesh.
    """
    edge = min(max(facts.pixel_mm, 0.5 * min(facts.ell_mm)), MAX_EDGE_PX * facts.pixel_mm)
    target = max(2000, int(facts.area_mm2 / (math.sqrt(3.0) / 4.0 * edge * edge)))
    return target if target * 2 <= facts.faces else None


def _blocked(receivers: float, sources: float) -> float:
    """Pairs the compiled pair sum evaluates for ``receivers`` x ``sources``: both padded to whole blocks.

    :func:`~torchsss.ops.fused.dipole_pair_sum` runs static blocks of 512 receivers x 2,048 sources on the CPU
    (padded with repeated receivers and zero-weight sources): 363 splats cost as many pairs as 2,048.
    """
    rb, sb = block_shape("cpu")
    return math.ceil(max(receivers, 1.0) / rb) * rb * math.ceil(max(sources, 1.0) / sb) * sb


def _pair_time(pairs: float, eager_t_pair: float, m: dict, warm: bool = False,
               another: bool = False, blocked: float | None = None, rate: str = "fused_t_pair") -> tuple[float, float]:
    """(seconds of one frame's ``pairs`` dipole pairs, one-time compile seconds) under the fused kernel's rule.

    The all-pairs dipole sum of the reference and the icdf and hybrid estimators runs in the compiled kernel of
    :mod:`torchsss.ops.fused` once a process has spent about one compile's worth of eager work
    (:data:`~torchsss.ops.fused.COLD_WORK` pairs): a frame of at least that many pairs is costed at the fused rate
    plus one compile in the setup; a smaller one at the eager rate (conservative when many frames follow). A kernel
    this process has already compiled (``warm``) costs no compile and serves every frame of
    :data:`~torchsss.ops.fused.WARM_WORK` pairs or more; ``TORCHSSS_COMPILE=off`` never compiles, ``on`` always does.
    A process that has compiled ``another`` variant of the pair sum pays ``fused_variant_s`` for this one instead
    of ``fused_compile_s`` (inductor is up; :data:`MODEL`). Compiled, the pairs counted are ``blocked``
    (:func:`_blocked`) where given, at the seconds per pair of the constant ``rate``.
    """
    if not compile_policy(pairs, warm=warm):
        return eager_t_pair * pairs, 0.0
    done = pairs if blocked is None else blocked
    return m[rate] * done, 0.0 if warm else m["fused_variant_s" if another else "fused_compile_s"]


def warm_kernels(device: str = "cpu", dtype: torch.dtype = torch.float32) -> frozenset[str]:
    """The fused dipole pair sums this process has already compiled: ``"plain"`` and ``"split"``.

    The reference and icdf run the plain pair sum, the hybrid the split one, splat's gather the truncated one
    (``"truncated"``). :func:`plan` charges a warm one no
    compile (a fresh ``python -m torchsss render`` pays one; a training loop or a notebook that rendered before
    does not).
    """
    return frozenset(kind for kind, split, trunc in (("plain", False, False), ("split", True, False),
                                                     ("truncated", False, True))
                     if is_warm("dipole_pair_sum", device=device, dtype=dtype, split=split, truncated=trunc))


def predict(method: str, knobs: dict, facts: SceneFacts, material, *, decimate: int | None = None,
            model: dict | None = None, sources: int | None = None,
            warm: frozenset[str] = frozenset()) -> dict[str, float]:
    """Predicted ``error``, ``setup_s`` and ``frame_s`` of ``method`` with ``knobs`` on a scene (see the module).

    Lensch's ``setup_s`` includes its first frame's profile evaluations (also given alone as ``first_s``).

    ``material`` is a :class:`~torchsss.physics.Material` (its tensors feed the alias error); ``sources`` is the
    reference's source count when it differs from the facts' (decimated sources); ``warm``: the fused pair-sum
    kernels this process has already compiled (:func:`warm_kernels`: ``"plain"``, ``"split"``), charged no compile.
    """
    m = {**MODEL, **(model or {})}
    prof = _Profile.of(material)
    if method in ATLAS_METHODS and knobs.get("source_faces"):  # built on the decimated mesh, camera on the full one
        decimate = int(knobs["source_faces"])
    faces = decimate or facts.faces
    dec_s = m["decimate_s_face"] * facts.faces if decimate else 0.0
    px, lights = facts.covered_px, facts.lights
    if method == "reference":
        eps = float(knobs.get("eps", TRUTH_EPS))
        n0 = facts.sources[0]
        n = facts.sources[REFERENCE_EPS.index(eps)] if eps in REFERENCE_EPS else n0
        if knobs.get("source_faces"):  # the decimated mesh's count, as ``sources_decimated``
            n = min(n, int(SOURCES_PER_FACE * int(knobs["source_faces"])))
        n = sources or n
        h_eff = math.sqrt(facts.area_mm2 / n)
        # the truth's effective spacing, but no finer than a fraction of the spacing it asks for: sources far denser
        # than that (a scan whose every face holds one: the shared igea's 268,686 at 0.057 mm where skin1 asks for
        # 0.61) add nothing a coarser candidate is measured against (not fitted, and no fitted row moves with it:
        # the two calibration scenes whose truth is that dense, a 10 mm skin1 igea and an 8 mm potato torus, have
        # rows only from their full meshes, whose every face keeps its source; the shared igea at 256 x 256 from
        # 18,685 and 11,160 faces: 0.24% and 0.38% measured, 1.64% and 2.35% predicted, the deviation included)
        h0 = max(math.sqrt(facts.area_mm2 / n0), m["ref_base"] * facts.spacing_mm)
        # the truth's own sources: the same image. Otherwise a resampled source set (a floor: a coarser eps that
        # keeps about as many sources, every face holding one, still moves them) and its effective spacing against
        # the truth's: sources on a decimated mesh are projected onto the full one (``project_sources``), so what
        # they lose is density
        same = eps == TRUTH_EPS and n == n0 and not knobs.get("source_faces")
        err = 0.0 if same else m["ref_err_floor"] + m["ref_err_n"] * max(h_eff / h0 - 1.0, 0.0) \
            + m["ref_err_alias"] * math.hypot(prof.alias(h_eff), prof.alias(h0))
        if knobs.get("source_faces") and eps in REFERENCE_EPS and facts.source_deviation_mm:
            # and how far the decimated surface strays: the dipole's relative change over a length d is about
            # d / (1/sigma_tr) (not fitted). Even projected, few sources on a coarse mesh miss more than their
            # density says: a side-lit 8 mm potato torus at 256 x 256 from 500 of its 2,304 faces measured 1.28%
            # where the density alone predicts 0.31%; with this charge 1.74% (at eps 0.3 from the same faces 1.97%
            # was measured: under by 12%, though still within a 2% plan). Conservative on scans (the back-lit 25 mm
            # apple igea from 11,484 and 5,625 faces: 0.43% and 1.11% measured, 1.08% and 1.88% predicted)
            err += facts.source_deviation_mm[REFERENCE_EPS.index(eps)] / min(facts.ell_mm)
        shadow = 0.2 if knobs.get("shadows") == "none" else 1.0
        pair_s, compile_s = _pair_time(px * n, m["ref_t_pair"], m, "plain" in warm, bool(warm),
                                       _blocked(px, n))
        frame = pair_s + shadow * m["ref_t_src"] * n * lights + m["ref_t_px"] * facts.pixels
        setup = m["ref_s0"] + m["ref_s_src"] * n + compile_s + (m["decimate_s_face"] * facts.faces
                                                                if knobs.get("source_faces") else 0.0)
        return {"error": err, "setup_s": setup, "frame_s": frame, "compile_s": compile_s}
    if method == "splat":
        eps, over = float(knobs.get("eps", 0.01)), float(knobs.get("oversample", 2.0))
        h = prof.spacing(eps)
        grid = grid_for(2.0 * facts.radius_mm, h, over)  # splat_grid's rule
        texel = 2.0 * facts.radius_mm / grid
        # the light view's texels per splat spacing as built (at least MIN_GRID x oversample, at most 512: a small
        # object is oversampled far more than asked)
        over_eff = h / texel
        r = prof.r_max(eps)
        # what the truncation at r_max drops from the seen radiosity, computed on the scene (not fitted; 3-D
        # distances: light that crossed a thick back-lit object is far); for an eps the facts do not hold, the
        # planar tail between r_max and the object's diameter (what a wide flat object loses)
        if facts.splat_truncation and eps in SPLAT_EPS:
            cut = facts.splat_truncation[SPLAT_EPS.index(eps)]
        else:
            cut = prof.tail_between(r, 2.0 * facts.radius_mm)
        u = max(facts.unlit, 0.1)
        # and the irradiance itself sampled at the object's scale: MIN_GRID texels across it at oversample 1 (a side-lit
        # 8 mm potato torus 1.9% at grid 32, 0.5% at 128, where its profile asks for a handful of texels), less on a
        # convex object, whose irradiance n.l has no shadows and varies smoothly
        obj = m["splat_obj"] * (m["splat_obj_convex"] if facts.convex else 1.0) * (MIN_GRID / grid) ** m["splat_obj_p"]
        err = math.sqrt((m["splat_floor"] * u ** m["splat_u_floor"]) ** 2 + obj ** 2
                        + (m["splat_alias"] * u ** m["splat_u_alias"] * prof.alias_share(eps) / over_eff ** 2) ** 2
                        + cut ** 2)
        footprint = min(px, math.pi * (r / facts.pixel_mm) ** 2)
        splats = facts.light_fill * grid * grid  # the light view's sources (texels that see the object, cut pieces)
        # eager (window or tile): the pairs in reach, each through the profile's table
        pairs_s, compile_s = m["splat_t"] * splats * footprint * lights, 0.0
        gather = px * splats
        if footprint >= GATHER_REACH * px and compile_policy(gather, warm="truncated" in warm):
            # splat_radiosity's rule for its gather form (a reach share of GATHER_REACH, the pairs compiled): every
            # (pixel, splat) pair in the fused pair sum, in whole blocks, its truncated variant compiled once per
            # process
            pairs_s, compile_s = _pair_time(gather, m["ref_t_pair"], m, "truncated" in warm, bool(warm),
                                            _blocked(px, splats), "splat_t_gather")
            pairs_s *= lights
        frame = pairs_s + m["splat_t_texel"] * grid * grid * lights + m["splat_f0"]
        return {"error": err, "setup_s": m["splat_s0"] + dec_s + compile_s, "frame_s": frame, "compile_s": compile_s}
    # the atlas methods' mesh decimated to ``faces``: its surface strays from the true one, as the reference's
    # decimated sources do (not fitted; the deviation scales as the squared edge, 1 / faces). Since the texels are lit
    # on the full mesh (AtlasView.lit_texels) a conservative bound, as the reference's: the shared igea's Lensch plan
    # (5,874 faces) is charged 3.45% and measured 1.13% in all, its icdf plan (17,139) 1.18% and 0.50%
    target = detail_faces(facts)
    atlas_dev = 0.0
    if method in ATLAS_METHODS and decimate and target and facts.atlas_deviation_mm:
        atlas_dev = facts.atlas_deviation_mm * max(1.0, target / faces) / min(facts.ell_mm)
    if method in ("icdf", "hybrid"):
        n = int(knobs.get("samples", 4096))
        res = int(knobs.get("atlas_resolution", 512))
        lit_s = m["transfer_s_texel"] * m["valid_fraction"] * res * res if decimate else 0.0
        setup = (m["icdf_s0"] + m["icdf_s_face"] * faces ** m["icdf_face_p"] + m["icdf_s_texel"] * res * res + dec_s
                 + lit_s)
        if method == "icdf":
            err = icdf_error(facts, n, m)
            pair_s, compile_s = _pair_time(px * n, m["icdf_t_pair"], m, "plain" in warm, bool(warm),
                                           _blocked(px, n))
            frame = pair_s + m["icdf_f0"]
            setup += compile_s
        else:
            _, stride, pairs, per = hybrid_split_plan(facts, m)
            err = hybrid_error(facts, n, m)
            # the split runs in the fused kernel too
            pair_s, compile_s = _pair_time(px * n, m["hybrid_t_pair"], m, "split" in warm, bool(warm),
                                           _blocked(px, n))
            exact = m["hybrid_exact_fraction"] * px * per if stride > 1 else 0.0
            local = pairs if stride >= 0 else HybridRenderer.defaults["max_local_pairs"]
            frame = pair_s + m["hybrid_f0"] + m["hybrid_t_local"] * local + m["hybrid_t_exact"] * exact
            setup += m["hybrid_s0"] + compile_s + m["hybrid_t_local_build"] * local
        return {"error": err + atlas_dev, "setup_s": setup, "frame_s": frame, "compile_s": compile_s}
    if method == "lensch":
        res = int(knobs.get("atlas_resolution", 512))
        texel = math.sqrt(facts.area_mm2 / (ATLAS_UTILIZATION * res * res))
        edge = facts.median_edge_mm * math.sqrt(facts.faces / faces)
        k = min(max(2 * round(0.7 * edge / texel) + 1, 5), 11)  # plan_kernel_size
        blend = 5 * texel / edge >= BLEND_MIN_REACH  # plan_lensch: blending only where the kernel reaches
        # the irradiance's detail at the hats' scale is answered only by the kernels, within their window and their
        # chart: charged as it is (not fitted; 0 on smooth meshes under smooth light)
        # the light the throughput's threshold cuts from the image (not fitted; 0 unless a large back-lit object of a
        # long-scattering material is lit only along entries below it)
        level = _threshold_level(float(knobs.get("threshold", THROUGHPUT_THRESHOLD)))
        cut = facts.throughput_cut[level] if facts.throughput_cut else 0.0
        err = math.hypot(m["lensch_floor"], m["lensch_texel"] * (texel / min(facts.ell_mm)) ** 3,
                         m["lensch_blend"] if blend else 0.0, facts.irradiance_detail, cut)
        setup = m["lensch_s0"] + m["lensch_s_face"] * faces + dec_s
        if decimate:  # the valid texels lit on the full mesh (AtlasView.lit_texels)
            setup += m["transfer_s_texel"] * m["valid_fraction"] * res * res
        if blend:
            setup += m["lensch_s_kernel"] * res * res * k * k
        # the first frame's profile evaluations (once per material): the full mesh's entries scaled by faces^2,
        # at most what the decimation rule keeps (0.9 of the cap); unknown (not estimated) counts none
        full = facts.throughput_entries_finer[level - 1] if level and facts.throughput_entries_finer \
            else facts.throughput_entries
        entries = min(max(full, 0) * (faces / facts.faces) ** 2, 0.9 * MAX_THROUGHPUT_ENTRIES)
        taps = m["lensch_t_tap_full"] * res * res * k * k if blend else m["lensch_t_tap"] * res * res * 49  # k = 7
        first = m["lensch_t_entry"] * entries + taps
        return {"error": err + atlas_dev, "setup_s": setup + first, "first_s": first,
                "frame_s": m["lensch_t_texel"] * res * res + m["lensch_f0"]}
    raise ValueError(f"method: expected one of reference, splat, icdf, hybrid, lensch, got {method!r}")


def _lensch_fit(faces: int, entries: int) -> int:
    """The faces at which Lensch's throughput (``entries`` on the full mesh of ``faces``) would keep 0.6 of the cap.

    Entries scale with the square of the vertex count where the profile reaches across the object (on the default
    scene within 1%: 6.30M estimated, 6.36M kept).
    """
    return int(faces * math.sqrt(0.6 * MAX_THROUGHPUT_ENTRIES / max(entries, 1)))


def _deviations(mesh: Mesh, given: Mesh, counts: Sequence[int]) -> dict[int, float]:
    """How far ``given`` decimated to each of ``counts`` faces strays from ``mesh`` (mm; :func:`surface_deviation`).

    Where there are four or more distinct counts, only the smallest, the middle and the largest are decimated and
    measured, and the others are interpolated between their neighbours as a power of the face count (a quadric
    decimation of a scan strays about as :math:`N^{-0.85}` to :math:`N^{-1.4}`): on the five verification scans
    with four or more counts (bunny, igea, teapot; 2026-11-29) within -2% to +11% of their own decimation (a bumpy
    sphere's -3% to +17%), while a scan's first plan decimates 3 times instead of 5-6 (0.1-0.2 s each on 30-40k
    faces, about 1 s on the shared igea's 268k).
    """
    ws = sorted(set(int(w) for w in counts))
    measured = ws if len(ws) < 4 else [ws[0], ws[len(ws) // 2], ws[-1]]
    dev = {w: surface_deviation(mesh, _source_mesh(given, w)) for w in measured}
    for w in ws:
        if w in dev:
            continue
        lo = max(m for m in measured if m < w)
        hi = min(m for m in measured if m > w)
        if dev[lo] > 0.0 and dev[hi] > 0.0:
            k = math.log(dev[hi] / dev[lo]) / math.log(hi / lo)
            dev[w] = dev[lo] * (w / lo) ** k
        else:  # a flat part: no power law through zero
            dev[w] = max(dev[lo], dev[hi])
    return dev


#: _source_mesh's memo: id of the mesh -> (mesh, {(faces, ladder): decimated}); a few meshes, each held while its
#: entry lives.
_DECIMATED: dict[int, tuple[Mesh, dict[tuple[int, bool], Mesh]]] = {}


def _source_mesh(mesh: Mesh, faces: int, *, ladder: bool = False) -> Mesh:
    """``mesh`` decimated to about ``faces`` faces (:func:`~torchsss.pipelines.atlas_view.source_mesh`), remembered.

    Planning decimates a scan to the same counts for the facts' surface deviations, the throughput cut, the
    throughput fit and the finer thresholds (the shared igea: about 1 s each), a few meshes' worth kept.
    ``ladder``: decimate from the coarsest decimation of ``mesh`` already made with at least ``faces`` faces, for a
    stand-in that no renderer builds on (:func:`sampling_spread`'s 3,000 faces; a mesh decimated in steps strays
    from the surface differently: on a bumpy 81,920-face sphere 23% less than the direct one, so the surface
    deviations are measured on direct decimations, as the renderers make them).
    """
    faces = int(faces)
    if faces >= mesh.num_faces:
        return mesh
    hit = _DECIMATED.get(id(mesh))
    if hit is None or hit[0] is not mesh:
        if len(_DECIMATED) >= 4:
            _DECIMATED.pop(next(iter(_DECIMATED)))
        hit = _DECIMATED[id(mesh)] = (mesh, {})
    levels = hit[1]
    key = (faces, ladder)
    if key not in levels:
        finer = [k for k in levels if k[0] >= faces] if ladder else []
        levels[key] = source_mesh(levels[min(finer)] if finer else mesh, faces)
    return levels[key]


def _threshold_level(threshold: float) -> int:
    """The index in :data:`LENSCH_THRESHOLDS` of the finest planned threshold at or above ``threshold``."""
    level = 0
    for i, t in enumerate(LENSCH_THRESHOLDS):
        if threshold <= t * (1.0 + 1e-9):
            level = i
    return level


def _throughput_fit(scene: Scene, mesh: Mesh | None, material: torch.nn.Module, faces: int) -> int:
    """Lensch's throughput decimation checked on the decimated mesh itself.

    ``faces``, or fewer when the vertex throughput of the mesh decimated to ``faces`` is estimated over 0.9 of
    :data:`MAX_THROUGHPUT_ENTRIES` (one decimation and one estimate; the builder refuses past the cap); or more,
    up to the full mesh, when that estimate leaves room under 0.85 of the cap and the mesh decimated to the larger
    count is estimated within 0.9 of it (a second decimation and estimate). The decimation is what limits Lensch on
    a long-scattering scan: the side-lit 30 mm marble bunny measured 3.0% at 5,360 faces (estimated 7.0e6
    entries) and 2.5% at 6,400 (9.6e6).
    """
    mesh = scene.load_mesh(dtype=torch.float64) if mesh is None else mesh  # the estimate works in float64
    est = estimate_throughput_entries(_source_mesh(mesh, faces), material, rows=64)
    if est > 0.9 * MAX_THROUGHPUT_ENTRIES:
        return int(faces * math.sqrt(0.8 * MAX_THROUGHPUT_ENTRIES / est))
    more = min(mesh.num_faces, int(faces * math.sqrt(0.85 * MAX_THROUGHPUT_ENTRIES / max(est, 1.0))))
    if more < 1.05 * faces:
        return faces
    if estimate_throughput_entries(_source_mesh(mesh, more), material, rows=64) <= 0.9 * MAX_THROUGHPUT_ENTRIES:
        return more
    return faces


def _finer_thresholds(scene: Scene, mesh: Mesh | None, facts: SceneFacts, material: torch.nn.Module,
                      planned: list[dict], decimate: int | None) -> list[dict]:
    """Lensch candidates at the finer thresholds of :data:`LENSCH_THRESHOLDS`, where the default one cuts light.

    "Model only what a scene requires": the far entries are kept only where the seen side is lit along them
    (:attr:`SceneFacts.throughput_cut` over :data:`CUT_MATTERS`), and only at a threshold whose throughput, on the
    mesh Lensch builds on, is estimated within 0.9 of :data:`MAX_THROUGHPUT_ENTRIES` (the builder refuses past the
    cap); each threshold's candidates copy the default's (every atlas size) with the threshold added and its rule.
    """
    if not facts.throughput_cut or facts.throughput_cut[0] <= CUT_MATTERS:
        for cand in planned:
            if cand["method"] == "lensch" and facts.throughput_cut:
                cand["rules"]["threshold"] = (f"threshold {THROUGHPUT_THRESHOLD:g} (default): it cuts "
                                              f"{facts.throughput_cut[0]:.2%} of the seen radiosity")
        return []
    default = [c for c in planned if c["method"] == "lensch" and "threshold" not in c["knobs"]]
    source = None
    out = []
    for level, t in enumerate(LENSCH_THRESHOLDS[1:], start=1):
        if facts.throughput_cut[level - 1] <= CUT_MATTERS:
            break  # the coarser threshold already keeps what the image needs
        if source is None:
            full = scene.load_mesh(dtype=torch.float64) if mesh is None else mesh
            source = _source_mesh(full, decimate) if decimate else full
        entries = estimate_throughput_entries(source, material, threshold=t, rows=64)
        why = (f"threshold {t:g}: the default {THROUGHPUT_THRESHOLD:g} cuts {facts.throughput_cut[0]:.2%} of the seen "
               f"radiosity (the seen side lit along long paths), {t:g} cuts {facts.throughput_cut[level]:.2%}")
        if entries > 0.9 * MAX_THROUGHPUT_ENTRIES:
            for cand in default:
                cand["rules"]["threshold"] = (f"{why}, but would keep ~{entries:.3g} entries on {source.num_faces} "
                                              "faces, over the cap: not offered")
            break
        for cand in default:
            cand["rules"]["threshold"] = f"threshold {THROUGHPUT_THRESHOLD:g} (default): it cuts " \
                                         f"{facts.throughput_cut[0]:.2%} of the seen radiosity"
            out.append({**cand, "knobs": {**cand["knobs"], "threshold": t},
                        "rules": {**cand["rules"], "threshold": f"{why} (~{entries:.3g} entries)"}})
    return out


def candidates(scene: Scene, facts: SceneFacts, tolerance: float,
               methods: Sequence[str] | None = None, model: dict | None = None, *,
               mesh: Mesh | None = None) -> list[dict]:
    """Every configuration the planner considers: ``{"method", "knobs", "decimate", "rules"}`` dicts.

    The knobs follow the rules (:data:`RULES`): the icdf/hybrid N from the tolerance, the reference's source
    decimation and shadows, the atlas methods' mesh decimation. ``mesh``: the scene's mesh if already loaded (Lensch's
    throughput decimation is checked on the decimated mesh).
    """
    allowed = applicable_methods(scene)
    methods = [m for m in (methods or allowed) if m in allowed]
    dec = detail_faces(facts)
    out: list[dict] = []
    prof = _Profile.of(scene.material)
    for method in methods:
        rules: dict[str, str] = {}
        decimate = dec if method in ATLAS_METHODS else None
        if decimate:
            rules["decimate"] = (f"{facts.faces} faces (median edge {facts.median_edge_mm:.3g} mm) -> {decimate}: "
                                 f"pixel {facts.pixel_mm:.3g} mm, shortest 1/sigma_tr {min(facts.ell_mm):.3g} mm")
        if method == "reference":
            for eps, n, wanted, n_dec in zip(REFERENCE_EPS, facts.sources, facts.source_faces,
                                             facts.sources_decimated):
                h = reference_spacing(prof, facts.size_mm, eps)
                # the full mesh's sources always, and those of the mesh decimated to the spacing where that saves
                # samples (its surface deviation adds error: on a small, finely tessellated object only the full
                # sources may meet a tight tolerance)
                variants = [(None, n)] + ([(wanted, n_dec)] if wanted * 2 <= facts.faces and n_dec * 1.5 <= n else [])
                for faces, count in variants:
                    knobs: dict = {"eps": eps}
                    r = dict(rules)
                    if faces is not None:
                        knobs["source_faces"] = faces
                        r["sources"] = (f"sources from {faces} faces, not {facts.faces}: the spacing {h:.3g} mm "
                                        f"needs about {count} samples")
                    if facts.convex and facts.lights > 0:
                        knobs["shadows"] = "none"
                        r["shadows"] = "convex object: a sample faces the light exactly when the light sees it"
                    out.append({"method": method, "knobs": knobs, "decimate": None, "rules": r, "_sources": count})
        elif method == "splat":
            # eps 0.1 is left out: the truncation drops 10% of every splat's energy, and where that shows (thin
            # parts of long-scattering materials, front-lit) is beyond the model: in the verification run all 9 of
            # its 27 planned renders with eps 0.1 (front-lit chicken1, chicken2, skin1) missed their tolerance
            for eps in SPLAT_EPS:
                for over in SPLAT_OVERSAMPLE:
                    r = dict(rules)
                    r["splat_budget"] = f"eps {eps} (r_max {prof.r_max(eps):.3g} mm), oversample {over}"
                    out.append({"method": method, "knobs": {"eps": eps, "oversample": over}, "decimate": None,
                                "rules": r})
        elif method in ("icdf", "hybrid"):
            m = {**MODEL, **(model or {})}
            # the error model predict() uses (hybrid_terms: the hybrid without a split as the icdf estimator, a
            # narrowed split also bounded by it with the narrowed split's spread); N meets every term
            terms = hybrid_terms(facts, m) if method == "hybrid" else [sampling_terms(facts, "icdf", m)]
            # the sampling error's share of the tolerance: what the decimated mesh's deviation leaves (predict)
            target = tolerance / MARGINS[method] - (facts.atlas_deviation_mm / min(facts.ell_mm) if decimate else 0.0)
            r = dict(rules)
            if method == "hybrid":
                scale, stride, _, _ = hybrid_split_plan(facts, m)
                if stride <= 0:
                    r["local_term"] = ("the surface local term's pairs do not fit even narrowed: N planned with the "
                                       "icdf estimator's error" if stride < 0 else
                                       "the split is off (the local bound reaches across the object, or narrowed "
                                       "away): every source sampled, N planned with the icdf estimator's error")
                elif scale > 1:
                    r["local_term"] = (f"the pairs do not fit at c = {HybridRenderer.defaults['c']:g}: the split "
                                       f"narrows to c = {HybridRenderer.defaults['c'] * scale:g}; N planned with the "
                                       f"larger of the hybrid's error and the icdf estimator's on the near field it "
                                       f"samples (one-sample spread {facts.narrowed_spread:.3g})")
            needs = [4096.0 * (a / math.sqrt(target * target - f * f)) ** (1.0 / p) if a > 0 else 0.0
                     for f, a, p in terms if target > f]
            n = 0
            if len(needs) == len(terms):
                n = int(2 ** math.ceil(math.log2(max(MIN_SAMPLES, *needs))))
                model_text = " and ".join(f"hypot({f:.3g}, {a:.3g} (4096 / N)^{p})" for f, a, p in terms)
                r["samples"] = (f"N = {n}: error ~ {model_text} meets {tolerance:.2%} with margin "
                                f"{MARGINS[method]}")
            if not 0 < n <= 1 << 18:
                # the floor alone misses, or more than 2^18 samples would be needed: the N at which sampling adds ~12%
                # to the floor (the most accurate worth having; a candidate predicted outside the tolerance, which
                # plan_method falls back to, where the method's default N 4096 measured 7.7% on the shared igea
                # at 3%), the sampling term taken with the method's margin as every planned error is (it held the N
                # of the back-lit 30 mm marble bunny at 4096, measured 3.9% against 2.5% at 8192)
                need = max(4096.0 * (MARGINS[method] * a / (0.5 * f)) ** (1.0 / p) if a > 0 else 0.0
                           for f, a, p in terms)
                n = int(2 ** math.ceil(math.log2(min(max(MIN_SAMPLES, need), float(1 << 16)))))
                floors = ", ".join(f"{f:.3g}" for f, _, _ in terms)
                r["samples"] = (f"N = {n}: {tolerance:.2%} is out of the estimator's reach (its floor {floors}, "
                                f"or more than 2^18 samples); sampling kept below half of the floor with margin "
                                f"{MARGINS[method]}")
            out.append({"method": method, "knobs": {"samples": n}, "decimate": decimate, "rules": r})
        elif method == "lensch":
            # 0.6 of the cap from the full mesh's estimate scaled by faces^2 (on the default scene within 1%: 6.30M
            # estimated, 6.36M kept), then checked on the decimated mesh itself: on the bunny the scaling ran
            # 1.6-1.7x low (the 50 mm example bunny at 256 x 256 was planned 1.01e7 entries, over the cap, and the
            # builder refused it); a cut under 5% is not worth its error (the default scene cut 5,856 -> 4,665 faces
            # measured 4.9% instead of 2.6% at 128 x 128)
            fit = _lensch_fit(facts.faces, facts.throughput_entries)
            if fit < 0.95 * facts.faces and (decimate is None or fit < decimate):
                decimate = max(500, _throughput_fit(scene, mesh, prof.module, fit))
                rules = {**rules, "decimate": (
                    f"{facts.faces} -> {decimate} faces: the vertex throughput would keep ~"
                    f"{facts.throughput_entries:.3g} entries (the profile reaches across the object), over the "
                    f"{MAX_THROUGHPUT_ENTRIES:.0e} that fit in 1-2 GB")}
            for res in (256, 512, 1024):
                r = dict(rules)
                edge = facts.median_edge_mm * math.sqrt(facts.faces / decimate) if decimate else facts.median_edge_mm
                texel = math.sqrt(facts.area_mm2 / (ATLAS_UTILIZATION * res * res))
                reach = 5 * texel / edge
                if res == 1024 and reach >= BLEND_MIN_REACH:
                    continue  # the blending fit at 1024 (res^2 k^2: a minute, GBs) was never measured to pay
                r["blend"] = (f"blending on: an 11 x 11 kernel reaches {reach:.2f} median edges"
                              if reach >= BLEND_MIN_REACH else
                              f"blending skipped: even an 11 x 11 kernel reaches only {reach:.2f} median edges "
                              f"(< {BLEND_MIN_REACH})")
                if facts.irradiance_detail > 0.0:
                    r["creases"] = (f"irradiance detail {facts.irradiance_detail:.1%} where creases meet charged: the "
                                    "radiosity beside them varies within a vertex hat, and the kernels cannot reach "
                                    "it across a chart seam")
                out.append({"method": method, "knobs": {"atlas_resolution": res}, "decimate": decimate, "rules": r})
            out += _finer_thresholds(scene, mesh, facts, prof.module, out, decimate)
    for cand in out:  # the atlas methods build on the decimated mesh; the camera sees the full one
        if cand["method"] in ATLAS_METHODS and cand["decimate"]:
            cand["knobs"] = {**cand["knobs"], "source_faces": int(cand["decimate"])}
            cand["decimate"] = None
            cand["rules"]["decimate"] += " (atlas and precompute; the camera sees the full mesh)"
    return out


def plan(scene: Scene, tolerance: float = 0.02, frames: int = 1, *, methods: Sequence[str] | None = None,
         trade: dict | None = None, model: dict | None = None, mesh: Mesh | None = None) -> Plan:
    """Plan ``scene``'s render: the cheapest configuration whose predicted error meets ``tolerance``.

    Args:
        scene: a single-object translucent scene (several objects: the reference; caustics scenes: refused).
        tolerance: the relative RMSE against the reference to meet, in (0, 1).
        frames: how many frames will follow one setup (the cost is setup + frames x frame).
        methods: restrict the methods considered (default: every applicable one).
        trade: a measured trade of this scene (:func:`torchsss.trade.trade`): its rows replace the predictions
            for the configurations it measured.
        model: overrides of :data:`MODEL`'s constants.
        mesh: the scene's mesh, if already loaded.

    Returns:
        The :class:`Plan`. When no candidate meets the tolerance, the reference at its default knobs (the truth,
        error 0 by definition).

    Raises:
        ValueError: a tolerance outside (0, 1), frames < 1, or a caustics scene.

    Examples:
        >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
        ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
        ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 16, "height": 16}})
        >>> p = plan(s, tolerance=0.05)
        >>> p.method in ("reference", "splat", "icdf", "hybrid", "lensch"), p.predicted_error <= 0.05
        (True, True)
    """
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) or not 0.0 < tolerance < 1.0:
        raise ValueError(f"tolerance: expected a number in (0, 1), got {tolerance!r}")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ValueError(f"frames: expected an int >= 1, got {frames!r}")
    if scene.caustics is not None:
        raise ValueError("scene: expected a translucent scene, got a caustics scene (render it with --method "
                         "caustics; the planner plans subsurface methods)")
    if len(scene.objects) > 1:
        return Plan("reference", {}, None, ["all-pairs dipole"], [], 0.0, math.nan, math.nan, float(tolerance),
                    frames, {"method": "several objects: the reference (the planner plans single objects)"})
    with validation(False):  # the scene's material and mesh were validated at load; the bisections run ~800 times
        return _plan(scene, float(tolerance), frames, methods, trade, model, mesh)


def _plan(scene: Scene, tolerance: float, frames: int, methods, trade, model, mesh) -> Plan:
    # once, for the facts and the candidates; float32 as the renderer loads it (one cached load for both)
    mesh = scene.load_mesh() if mesh is None else mesh
    m = {**MODEL, **(model or {})}
    # Lensch's error is at least its floor: when that misses the tolerance (and Lensch was not asked for by name or
    # measured), it is not costed, and its throughput estimate is not computed
    floor = m["lensch_floor"] * MARGINS["lensch"]
    chosen = methods is None and trade is None  # every applicable method, none measured: the gates below apply
    lensch_out = chosen and floor > tolerance
    if lensch_out:
        methods = [x for x in applicable_methods(scene) if x != "lensch"]
    # nor when its setup and frames alone (before the throughput and the blending fit) cost more than the best
    # other plan: its throughput estimate is the costliest fact (0.3 s on a 40k-face scan)
    lensch_bound = m["lensch_s0"] + frames * m["lensch_f0"]
    lensch_last = not lensch_out and chosen and "lensch" in applicable_methods(scene)
    # likewise the Monte Carlo estimators: their one-sample spread (0.15 s of a small scene's 0.25 s of facts) only
    # where their setup and frames at the fewest samples could beat the best other plan (also when Lensch's floor
    # ruled it out above: until 2026-11-29 that narrowed ``methods`` and switched this gate off at 1%, where every
    # first plan of a scene computed the spread, 0.2-0.4 s of its 0.3-0.7 s)
    sampled_last = chosen
    later = ("lensch",) * lensch_last + ("icdf", "hybrid") * sampled_last
    first = [x for x in (methods or applicable_methods(scene)) if x not in later] if later else methods
    facts = SceneFacts.from_scene(scene, mesh, throughput=not (lensch_out or lensch_last), spread=not sampled_last)
    measured = _measured(trade)
    warm = warm_kernels()

    def costed(facts: SceneFacts, methods) -> list[dict]:
        rows = []
        for cand in candidates(scene, facts, float(tolerance), methods, model, mesh=mesh):
            knobs = dict(cand["knobs"])
            pred = predict(cand["method"], knobs, facts, scene.material, sources=cand.get("_sources"),
                           decimate=cand["decimate"], model=model, warm=warm)
            key = _key(cand["method"], knobs, cand["decimate"])
            source = "model"
            if key in measured:
                pred, source = {**pred, **measured[key]}, "measured"
            total = pred["setup_s"] + frames * pred["frame_s"]
            rows.append({**cand, **pred, "total_s": total, "source": source})
        return [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]

    def meets(r: dict) -> bool:
        return r["error"] * MARGINS[r["method"]] <= tolerance or (r["source"] == "measured"
                                                                    and r["error"] <= tolerance)

    rows = costed(facts, first)
    skipped: dict[str, str] = {}
    estimators = [x for x in ("icdf", "hybrid") if sampled_last and x in applicable_methods(scene)]
    if estimators:
        best_other = min((r["total_s"] for r in rows if meets(r)), default=math.inf)
        # each at the fewest samples its rule plans (MIN_SAMPLES), its setup with its decimation: a lower bound
        bounds = {}
        for cand in candidates(scene, facts, float(tolerance), estimators, model, mesh=mesh):
            pred = predict(cand["method"], {**cand["knobs"], "samples": int(MIN_SAMPLES)}, facts, scene.material,
                           decimate=cand["decimate"], model=model, warm=warm)
            bounds[cand["method"]] = pred["setup_s"] + frames * pred["frame_s"]
        keep = [x for x in estimators if bounds.get(x, 0.0) < best_other]
        for x in estimators:
            if x not in keep:
                skipped[x] = (f"not costed: its setup and {frames} frame(s) at {int(MIN_SAMPLES)} samples alone "
                              f"(>= {bounds[x]:.2f} s) exceed the best other plan's {best_other:.2f} s")
        if keep:
            facts = SceneFacts.from_scene(scene, mesh, throughput=not (lensch_out or lensch_last))
            rows += costed(facts, keep)
    if lensch_last:
        best_other = min((r["total_s"] for r in rows if meets(r)), default=math.inf)
        if best_other <= lensch_bound:
            skipped["lensch"] = (f"not costed: its setup and {frames} frame(s) alone (>= {lensch_bound:.2f} s "
                                 f"before the throughput and the blending) exceed the best other plan's "
                                 f"{best_other:.2f} s")
        else:
            facts = SceneFacts.from_scene(scene, mesh, throughput=True, spread=facts.sampling_spread >= 0)
            rows += costed(facts, ["lensch"])
    rows.sort(key=lambda r: r["total_s"])
    ok = [r for r in rows if meets(r)]
    if ok:
        best = ok[0]
    else:
        best = {"method": "reference", "knobs": {}, "decimate": None, "rules": {}, "total_s": math.nan,
                "error": 0.0, "setup_s": math.nan, "frame_s": math.nan}
    reasons = _reasons(best, rows, float(tolerance), frames, bool(ok), warm)
    if lensch_out and "lensch" in applicable_methods(scene):
        reasons["lensch"] = (f"not costed: its error floor {floor / MARGINS['lensch']:.1%} (x margin "
                             f"{MARGINS['lensch']}) exceeds {tolerance:.2%}")
    reasons.update(skipped)
    modelled, skipped = _terms(best, scene)
    return Plan(method=best["method"], knobs=dict(best["knobs"]), decimate=best["decimate"], modelled=modelled,
                skipped=skipped, predicted_error=best["error"], predicted_setup_s=best["setup_s"],
                predicted_frame_s=best["frame_s"], tolerance=float(tolerance), frames=frames, reasons=reasons,
                facts=dataclasses.asdict(facts), candidates=rows)


def _key(method: str, knobs: dict, decimate: int | None) -> str:
    return json.dumps([method, {k: knobs[k] for k in sorted(knobs)}, decimate])


def _measured(trade: dict | None) -> dict[str, dict]:
    if not trade:
        return {}
    out = {}
    for row in trade.get("rows", []):
        knobs = dict(row["knobs"])
        dec = knobs.pop("decimate", None)
        out[_key(row["method"], knobs, dec)] = {"error": row["rel_rmse"], "setup_s": row["setup_s"],
                                                "frame_s": row["frame_s"]}
    return out


def _reasons(best: dict, rows: list[dict], tolerance: float, frames: int, found: bool,
             warm: frozenset[str]) -> dict:
    reasons: dict[str, str] = {}
    if not found:
        reasons["method"] = (f"no faster configuration is predicted to meet {tolerance:.2%}: the reference at its "
                             "default knobs (the truth)")
        return reasons
    beaten = []
    for m in dict.fromkeys(r["method"] for r in rows if r["method"] != best["method"]):
        mine = [r for r in rows if r["method"] == m]
        good = [r for r in mine if r["error"] * MARGINS[m] <= tolerance]
        beaten.append(f"{m} {min(r['total_s'] for r in good):.1f} s" if good else
                      f"{m} best predicted {min(r['error'] for r in mine):.1%}")
    reasons["method"] = (f"{best['method']}: cheapest predicted to meet {tolerance:.2%} over {frames} frame(s) "
                         f"({best['total_s']:.2f} s; {'; '.join(beaten) or 'no other method applies'})")
    if best["method"] == "reference":
        reasons["reference"] = "the reference itself is the cheapest way to the tolerance here"
    if best["method"] in ("reference", "icdf", "hybrid") or best.get("compile_s"):
        reasons["compile"] = (f"one compile of the fused pair sum charged ({best['compile_s']:.1f} s of the setup"
                              f"{'; another variant is compiled in this process' if warm else ''})"
                              if best.get("compile_s") else
                              "the fused pair sum is already compiled in this process: no compile charged"
                              if warm else "the pair sum runs eagerly: no compile")
    reasons.update(best.get("rules", {}))
    return reasons


def _terms(best: dict, scene: Scene) -> tuple[list[str], list[str]]:
    m, k = best["method"], best["knobs"]
    modelled = {"reference": ["all-pairs dipole"], "splat": ["splatted dipole (light-view sources)"],
                "icdf": ["importance-sampled global term"], "hybrid": ["local filter", "importance-sampled global"],
                "lensch": ["local kernels", "vertex throughput"]}[m][:]
    skipped = []
    if not any(hasattr(light, "position") or hasattr(light, "direction") for light in scene.lights):
        modelled.append("environment light (unshadowed, Shah 6.4.2)")
    elif k.get("shadows") == "none":
        skipped.append("shadow rays")
    else:
        modelled.append("shadows")
    if k.get("source_faces"):
        skipped.append(f"source detail beyond {k['source_faces']} faces")
    if best.get("decimate"):
        skipped.append(f"mesh detail beyond {best['decimate']} faces")
    return modelled, skipped


def plan_method(scene: Scene, method: str, tolerance: float = 0.02, frames: int = 1) -> tuple[dict, int | None, str]:
    """The default knobs of ``method`` for ``scene``: the planner's choice for that method alone.

    ``(knobs, decimate, note)``: the cheapest configuration of ``method`` predicted within ``tolerance``; when none
    is, its candidate with the smallest predicted error (``note`` says so); when the planner has no candidate of
    the method at all, no knobs (the method's own defaults). ``decimate`` is the scene's decimation (None for every
    method today: the atlas methods decimate through their ``source_faces`` knob).

    Raises:
        ValueError: as :func:`plan`.
    """
    p = plan(scene, tolerance, frames, methods=[method])
    if p.method == method:
        return dict(p.knobs), p.decimate, f"planned for {100 * tolerance:g}%: predicted {p.predicted_error:.2%}"
    mine = [c for c in p.candidates if c.get("method") == method and math.isfinite(c.get("error", math.nan))]
    if not mine:  # the method's defaults, on the detail an atlas needs (the decimation of a loose plan)
        loose = plan(scene, 0.5, frames, methods=["icdf"]).knobs.get("source_faces") if method in ATLAS_METHODS \
            else None
        return ({"source_faces": loose} if loose else {}), None, "no candidate: the method's defaults"
    best = min(mine, key=lambda c: c["error"])
    return (dict(best["knobs"]), best.get("decimate"),
            f"no configuration predicted within {100 * tolerance:g}%: the most accurate "
            f"({best['error']:.2%} predicted, {MARGINS.get(method, MARGIN) * best['error']:.2%} with the "
            f"planner's safety margin {MARGINS.get(method, MARGIN):g})")
