"""A geoloc labels' adjustment problem (:class:`geoloc.adjustment.AdjustmentProblem`) as
pycolmap's bundle adjustment: the same observations, start values and robust losses, solved
by COLMAP's Ceres bundle adjuster with the label priors added as COLMAP's own pose-prior
cost functions. Used by ``benchmarks/adjustment.py`` and ``tests/test_adjustment.py``.

The mapping. The labels' frame is a rig whose reference sensor is a stand-in (an IMU, no
data) and whose one camera sits at ``cam_from_rig`` = X⁻¹ (X = label_from_cam, refined as
``sensor_from_rig``); keyframe k is a frame with ``rig_from_world`` = B_k⁻¹ and one image
holding its observations; each point is a 3D point with its track. COLMAP holds the
offset constant when the rig's reference sensor has no images; the label priors constrain it
here, so it is made variable again. The camera is COLMAP's
PINHOLE with geoloc's (fx, fy, cx, cy), held constant. Reprojection residuals: COLMAP's, in
pixels, under ``HuberLoss(2)`` (σ_px = 1). Label prior of keyframe k:
``AbsolutePosePriorCost`` on ``rig_from_world`` with the prior L_k⁻¹ and covariance
diag(σ_r² I₃, σ_t² I₃) under ``CauchyLoss(3)``; the offset's prior the same on
``sensor_from_rig`` around the identity, diag(0.2² I₆), no loss. Ceres' cost is ½ Σ ρ; geoloc's
Σ ρ: :func:`cost` returns Ceres' cost doubled. COLMAP's prior residual is
(log(R_B⁻¹R_L), t(B⁻¹L)) where geoloc's is −log(L⁻¹B)^∨ reordered: equal to first order, so
the two cost functions agree exactly where the priors are at zero (the start) and to second
order in the corrections elsewhere (``benchmarks/adjustment.py`` evaluates both at both
solutions).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

import pyceres
import pycolmap
import pycolmap.cost_functions as colmap_costs

#: geoloc's adjustment defaults (geoloc-core ``AdjustmentOptions``): Huber width on the pixel
#: residual (σ_px = 1), Cauchy width on the label prior, the offset prior's σ (m, rad).
PIXEL_HUBER = 2.0
LABEL_CAUCHY = 3.0
OFFSET_SIGMA = (0.2, 0.2)
CAMERA = pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=1)


def _inverse(t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def rigid(t: np.ndarray) -> Any:
    """A 4×4 rigid transform as a ``pycolmap.Rigid3d``."""
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.ascontiguousarray(t[:3, :3])), np.ascontiguousarray(t[:3, 3]))


def _matrix(r: Any) -> np.ndarray:
    m = np.asarray(r.matrix())
    return m if m.shape == (4, 4) else np.vstack([m, [0.0, 0.0, 0.0, 1.0]])


@dataclass
class ColmapAdjustment:
    """The problem in pycolmap: the reconstruction (which owns the parameters), COLMAP's
    bundle adjuster and its Ceres problem with the priors added, and its options. Every
    object the problem points to is held here (Ceres does not keep Python objects alive)."""

    reconstruction: Any
    point_ids: list[int]
    options: Any
    config: Any
    adjuster: Any
    problem: Any
    held: list[Any]

    def _offset_params(self) -> np.ndarray:
        # the rig's dict of non-reference sensors holds the parameters the problem uses
        # (``Rig.sensor_from_rig`` returns a copy)
        params: np.ndarray = self.reconstruction.rig(1).non_ref_sensors[CAMERA].params
        return params

    def state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(B (K, 4, 4) world_from_label, X (4, 4) label_from_cam, points (N, 3))."""
        rec = self.reconstruction
        labels = np.array([_inverse(_matrix(rec.frame(k + 1).rig_from_world)) for k in range(rec.num_frames())])
        offset = _inverse(_matrix(rec.rig(1).non_ref_sensors[CAMERA]))
        points = np.array([rec.point3D(i).xyz for i in self.point_ids])
        return labels, offset, points

    def set_state(self, labels: np.ndarray, offset: np.ndarray, points: np.ndarray) -> None:
        """Writes B, X and the points into the parameters the problem optimizes."""
        rec = self.reconstruction
        for k, b in enumerate(labels):
            rec.frame(k + 1).rig_from_world.params[:] = rigid(_inverse(b)).params
        self._offset_params()[:] = rigid(_inverse(offset)).params
        for i, p in zip(self.point_ids, points):
            rec.point3D(i).xyz[:] = p

    def solver_options(self, threads: int, max_iterations: int | None = None) -> Any:
        """COLMAP's solver options for this problem (it picks the linear solver by size)."""
        so = self.options.ceres.create_solver_options(self.config, self.problem)
        so.num_threads = threads
        if max_iterations is not None:
            so.max_num_iterations = max_iterations
        return so

    def solve(self, threads: int, max_iterations: int | None = None) -> Any:
        """Solves in place; the Ceres summary."""
        summary = pyceres.SolverSummary()
        pyceres.solve(self.solver_options(threads, max_iterations), self.problem, summary)
        return summary

    def cost(self) -> float:
        """The cost at the current parameters, in geoloc's convention (Σ ρ, Ceres' doubled)."""
        so = pyceres.SolverOptions()
        so.max_num_iterations = 0
        summary = pyceres.SolverSummary()
        pyceres.solve(so, self.problem, summary)
        return 2.0 * float(summary.initial_cost)


def colmap_adjustment(problem: Any, label_sigma: tuple[float, float], width: int = 640, height: int = 480) -> ColmapAdjustment:
    """``problem`` (an AdjustmentProblem, started at its labels, X = I) as pycolmap's bundle
    adjustment with label priors of σ ``label_sigma`` (m, rad); see the module doc."""
    fx, fy, cx, cy = problem.intrinsics
    rec = pycolmap.Reconstruction()
    rec.add_camera(pycolmap.Camera(camera_id=1, model="PINHOLE", width=width, height=height, params=[fx, fy, cx, cy]))
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(pycolmap.sensor_t(type=pycolmap.SensorType.IMU, id=1))
    rig.add_sensor(CAMERA, pycolmap.Rigid3d())
    rec.add_rig(rig)
    keyframes = np.asarray(problem.obs_keyframes)
    order = np.argsort(keyframes, kind="stable")
    row_in_image = np.empty(len(keyframes), dtype=np.int64)
    for k, label in enumerate(problem.labels):
        rows = order[np.searchsorted(keyframes[order], k) : np.searchsorted(keyframes[order], k, side="right")]
        row_in_image[rows] = np.arange(len(rows))
        frame = pycolmap.Frame(frame_id=k + 1, rig_id=1)
        frame.rig_from_world = rigid(_inverse(label))
        image = pycolmap.Image(
            image_id=k + 1,
            name=str(k),
            camera_id=1,
            frame_id=k + 1,
            points2D=[pycolmap.Point2D(np.asarray(problem.obs_pixels[r], dtype=np.float64)) for r in rows],
        )
        frame.add_data_id(image.data_id)
        rec.add_frame(frame)
        rec.add_image(image)
        rec.register_frame(k + 1)
    tracks = [pycolmap.Track() for _ in range(len(problem.points))]
    for row, (k, j) in enumerate(zip(keyframes, problem.obs_points)):
        tracks[int(j)].add_element(int(k) + 1, int(row_in_image[row]))
    point_ids = [rec.add_point3D(np.asarray(p, dtype=np.float64), t) for p, t in zip(problem.points, tracks)]

    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = False
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.refine_sensor_from_rig = True
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.HUBER
    options.ceres.loss_function_scale = PIXEL_HUBER
    config = pycolmap.BundleAdjustmentConfig()
    for k in range(len(problem.labels)):
        config.add_image(k + 1)
    config.set_constant_cam_intrinsics(1)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, rec)
    out = ColmapAdjustment(rec, point_ids, options, config, adjuster, adjuster.problem, [])

    sigma_t, sigma_r = label_sigma
    prior = np.diag([sigma_r**2] * 3 + [sigma_t**2] * 3)
    for k, label in enumerate(problem.labels):
        block = rec.frame(k + 1).rig_from_world.params
        if not out.problem.has_parameter_block(block):
            raise RuntimeError(f"frame {k + 1}'s pose is not a parameter of COLMAP's problem")
        cost, loss = colmap_costs.AbsolutePosePriorCost(prior, rigid(_inverse(label))), pyceres.CauchyLoss(LABEL_CAUCHY)
        out.held += [cost, loss, block]
        out.problem.add_residual_block(cost, loss, [block])
    offset_block = out._offset_params()
    if not (out.problem.has_parameter_block(offset_block) and out.problem.has_manifold(offset_block)):
        raise RuntimeError("the camera's sensor_from_rig is not a parameter of COLMAP's problem")
    # COLMAP holds a rig's sensor_from_rig constant when the rig's reference sensor has no
    # images (nothing else would constrain the rig's poses); the label priors do here
    out.problem.set_parameter_block_variable(offset_block)
    offset_prior = np.diag([OFFSET_SIGMA[1] ** 2] * 3 + [OFFSET_SIGMA[0] ** 2] * 3)
    cost = colmap_costs.AbsolutePosePriorCost(offset_prior, pycolmap.Rigid3d())
    out.held += [cost, offset_block]
    out.problem.add_residual_block(cost, None, [offset_block])
    return out
