"""The problem and the state of a refinement: everything that stays fixed
(:class:`_Problem`, made by :func:`~._preparation._prepare_problem`), where a loop stands
(:class:`_State`), what it returns (:class:`_LoopOutcome`) and its history
records (:func:`_step_record`).

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._crystal import (
    _Crystal,
)
from kikuchipy_geomdic.calibration._phases import (
    _best_variants,
    _by_phase,
    _grain_labels,
    _sub_problems,
)
from kikuchipy_geomdic.calibration._processing import (
    PSF_NEGLIGIBLE,
    _compared,
    _fit_lobe,
    _gaussian_blur,
    _ncc,
    _with_mean_bands,
)
from kikuchipy_geomdic.calibration._systematic import _grains
from kikuchipy_geomdic.calibration.jacobian import (
    UNIQUE_AXIS_SYSTEMS,
    analytic_jacobian,
    finite_difference_jacobian,
)
from kikuchipy_geomdic.geometry import MapGeometry, rotation_vectors
from kikuchipy_geomdic.indexing import orientation as ori
from kikuchipy_geomdic.indexing._point_refinement import _VARIANT, _refine_points
from kikuchipy_geomdic.indexing._projection import PhaseArrays
from kikuchipy_geomdic.indexing.reindex import refine_orientations
from kikuchipy_geomdic.indexing.variants import _proper_rotations, _variant_table
from kikuchipy_geomdic.patterns import displacement as dsp

#: Simulations a problem keeps (:meth:`_Problem.simulate`): the next
#: stage asks for the last ones again (the DIC stage for the start's, the
#: full field's processing estimate for the DIC stage's last).
SIMULATIONS_KEPT = 2

#: Paper solver: smallest side (px) the patterns are binned down to for
#: the orientation refinements inside the loop. Orientations refined from
#: 60 px patterns were as precise (0.0025 deg) as from 120 px ones
#: (0.0022 deg) at a quarter of the cost.
LOOP_MIN_SIZE = 60


@dataclass(frozen=True)
class _Problem:
    """Everything that stays fixed during a refinement."""

    experimental: np.ndarray
    points: np.ndarray
    start_rotations: Rotation
    master_pattern: EBSDMasterPattern
    energy: float
    phase: Any
    parameters: tuple[str, ...]
    steps: dict[str, float]
    dic_kwargs: dict
    refine_kwargs: dict
    pseudo_symmetry_ops: Rotation | None = None
    #: The signal's static background, bands and all (float64), if it has one
    background: np.ndarray | None = field(default=None, repr=False)
    #: The crystal model, if the points are taken as one crystal
    crystal: _Crystal | None = None
    #: Whether the map's mean pattern, bands and all, was divided out of
    #: the patterns (:func:`_bands_divided_out`)
    mean_divided: bool = False
    #: Standard deviation of the crystal's c/a about the master pattern's
    #: phase's, as a fraction (0: held at it; inf: free)
    lattice_tolerance: float = 0.0
    #: The crystal's c axis over the phase's, as simulated (:attr:`arrays`)
    stretch: float = 1.0
    #: The phases calibrated from (:class:`PhaseToRefine`); the first is
    #: :attr:`master_pattern`, :attr:`phase` and :attr:`pseudo_symmetry_ops`
    phases: tuple = ()
    #: Index into :attr:`phases` of each point's phase (N,)
    point_phase: np.ndarray | None = field(default=None, repr=False)
    #: Gaussian point spread (px) the DIC stage's simulations are blurred
    #: by (:meth:`compare`); 0: as simulated
    point_spread: float = 0.0

    #: The last simulations (:meth:`simulate`) by their inputs, shared with
    #: the problems replaced from this one (the inputs are the key)
    simulations: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def multi_phase(self) -> bool:
        """Whether the points are of several phases: each phase's points
        are then answered by their one-phase problem (:attr:`sub_problems`)."""
        return len(self.phases) > 1

    @cached_property
    def sub_problems(self) -> list:
        """(rows, one-phase problem of those points) per phase with points
        (:func:`~kikuchipy_geomdic.calibration._phases._sub_problems`)."""
        return _sub_problems(self)

    @property
    def lattice_prior(self) -> float | None:
        """The prior's standard deviation of the c axis' stretch that the
        full field fits, or None where it is not fitted: held (a
        :attr:`lattice_tolerance` of 0), a lattice without one unique axis
        (cubic: no stretch that keeps its symmetry moves a band) or a
        polycrystal. There each pattern's own rotation absorbs most of a
        lattice error: a c/a 0.6 % off moved BaTiO3 polycrystals' PC by
        1.2e-4 at most (1.6 standard errors), and the fitted stretch was
        biased by 40 % at 0.01 % standard errors (the simulators'
        difference, which every grain shares). Nor where the map's mean was
        divided out of one crystal's patterns: the division, modelled with
        the data's own mean, left a stretch of 0.19 % at 20 standard errors
        on a domain map of the CIF's lattice (PC 2.6 -> 8.9e-4 off)."""
        if not self.lattice_tolerance > 0 or self.crystal is None or self.mean_divided:
            return None
        if self.phase.point_group.system not in UNIQUE_AXIS_SYSTEMS:
            return None
        return float(self.lattice_tolerance)

    def lattice_arrays(self, stretch: float) -> ori.MasterPatternArrays:
        """The master pattern's arrays projecting a crystal whose c axis is
        *stretch* times the phase's."""
        a = self._phase_arrays
        return a if stretch == 1.0 else ori.MasterPatternArrays(a.upper, a.lower, 0.0, stretch)

    def lattice_result(self, stretch: float, standard_error: float) -> dict[str, Any]:
        """What the calibration reports of the lattice fitted: the c axis'
        *stretch* (with its *standard_error*) against the phase's, the
        c/a it makes, whether the map determines it (its standard
        error below half the prior's, :attr:`lattice_tolerance`) and, with
        pseudo-symmetry operators, whether it still tells the variants
        apart (c/a beyond 3 standard errors of the parent's 1, or held
        near the CIF's by the prior where the map does not determine it)."""
        lat = self.phase.structure.lattice
        ratio = lat.c / lat.a
        determined = bool(standard_error < 0.5 * self.lattice_tolerance)
        return {
            "stretch": float(stretch - 1),
            "stretch_se": float(standard_error),
            "c_over_a": float(ratio * stretch),
            "c_over_a_se": float(ratio * standard_error),
            "phase_c_over_a": float(ratio),
            "tolerance": float(self.lattice_tolerance),
            "determined": determined,
            "variants_apart": bool(
                self.pseudo_symmetry_ops is None
                or not determined
                or abs(ratio * stretch - 1) > 3 * ratio * standard_error
            ),
        }

    @cached_property
    def lobe(self) -> np.ndarray | None:
        """The background lobe (mean 1) of the static background."""
        return None if self.background is None else _fit_lobe(self.background)

    @cached_property
    def grain_group(self) -> np.ndarray:
        """The rotations (m, 4) under which two orientations are one
        grain's: the crystal's proper rotations, times the variant
        operators if there are any."""
        symmetry = self.phase.point_group
        if self.multi_phase:
            raise ValueError("The points are of several phases: ask grains() of them")
        if self.pseudo_symmetry_ops is None:
            return _proper_rotations(symmetry)
        return _variant_table(self.pseudo_symmetry_ops, symmetry)[0].reshape(-1, 4)

    def grains(self, q: np.ndarray) -> np.ndarray:
        """Grain labels (N,) of the orientations *q* (N, 4) under
        :attr:`grain_group` (each phase's own, with several phases)."""
        if self.multi_phase:
            return _grain_labels(self, q)
        return _grains(q, self.grain_group)

    @cached_property
    def _phase_arrays(self) -> ori.MasterPatternArrays | PhaseArrays:
        """The master pattern's hemispheres at the energy, its phase's
        lattice; with several phases each point's phase's."""
        if self.multi_phase:
            arrays = tuple(p.arrays(self.energy) for p in self.phases)
            return PhaseArrays(arrays, np.asarray(self.point_phase))
        return ori.master_pattern_arrays(self.master_pattern, self.energy)

    @cached_property
    def arrays(self) -> ori.MasterPatternArrays:
        """The master pattern's hemispheres at the energy, for projection,
        of a crystal whose c axis is :attr:`stretch` times the phase's."""
        return self.lattice_arrays(self.stretch)

    def simulate(
        self,
        geometry: MapGeometry,
        rotations: Rotation,
        arrays: ori.MasterPatternArrays | None = None,
    ) -> np.ndarray:
        """Patterns (N, rows, columns), float64, read-only, as kikuchipy's
        ``get_patterns`` projects them, by this package's compiled
        kernel (a quarter of kikuchipy's time on 100 patterns), from
        *arrays* (default :attr:`arrays`). The last
        :data:`SIMULATIONS_KEPT` are kept by their inputs and returned
        again for the same ones."""
        det = geometry.detector(self.points)
        arrays = self.arrays if arrays is None else arrays
        q = np.ascontiguousarray(Rotation(rotations).flatten().data, dtype=np.float64)
        pcs, om = ori.detector_pcs(det, len(q)), ori.detector_matrix(det)
        # The master patterns' arrays by their memory, which the kept
        # simulation's reference holds: an id could be another's later
        several = isinstance(arrays, PhaseArrays)
        parts = arrays.phases if several else (arrays,)
        mp = tuple(
            (a.__array_interface__["data"][0], a.shape, a.strides, a.dtype.str, p.stretch)
            for p in parts
            for a in (p.upper, p.lower)
        )
        labels = arrays.labels.tobytes() if several else b""
        key = (q.tobytes(), pcs.tobytes(), om.tobytes(), tuple(det.shape), mp, labels)
        if key in self.simulations:
            return self.simulations[key][1]
        sim = ori.project_arrays(q, pcs, om, arrays, det.shape)
        sim.setflags(write=False)
        while len(self.simulations) >= SIMULATIONS_KEPT:
            del self.simulations[next(iter(self.simulations))]
        self.simulations[key] = (arrays, sim)
        return sim

    @property
    def bands_put_back(self) -> bool:
        """Whether the DIC stage sees the patterns with the map's mean bands
        put back (:attr:`dic_experimental`): the mean was divided out of
        one crystal's patterns. A few grains' mean holds other grains'
        bands too, and the test of :func:`_bands_divided_out` cannot tell
        them from one crystal at low doses (Ni, 6 grains, 30 counts/px:
        the background correlated 0.30 with the simulations, the patterns
        0.28), where the patterns as they are calibrate (PC 1.3e-3 and
        2.3e-3 off, within 3 standard errors; refused with the bands put
        back)."""
        return self.mean_divided and self.crystal is not None

    @cached_property
    def dic_experimental(self) -> np.ndarray:
        """The patterns (N, rows, columns), float32, the DIC stage compares
        with simulations: the experimental ones, or, where the map's mean
        was divided out of one crystal's (:attr:`bands_put_back`), those
        with the static background's bands put back
        (:func:`_with_mean_bands`)."""
        if not self.bands_put_back:
            return self.experimental
        return _with_mean_bands(self.experimental, self.background)

    @cached_property
    def compared_experimental(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The patterns (N, P) as float64, as the full field compares them
        (with the crystal model less their blur, :func:`_compared`; else
        the same array) and those centred: the same at every full-field
        iteration, which made them again. Not to be written to."""
        n = len(self.points)
        raw = self.experimental.reshape(n, -1).astype(np.float64)
        shape = tuple(self.experimental.shape[1:])
        e = raw if self.crystal is None else _compared(raw, shape)
        return raw, e, e - e.mean(axis=1, keepdims=True)

    def compare(
        self, geometry: MapGeometry, rotations: Rotation
    ) -> tuple[dsp.DisplacementField, np.ndarray]:
        """Displacement field and NCC (N,) of the patterns simulated at
        *geometry* (blurred by :attr:`point_spread`) against the
        experimental ones (:attr:`dic_experimental`), from one simulation."""
        sim = self.simulate(geometry, rotations).astype(np.float32)
        if self.point_spread >= PSF_NEGLIGIBLE:
            sim = _gaussian_blur(sim, self.point_spread, sim.shape[1:])
        field = _measure(sim, self.dic_experimental, self.dic_kwargs)
        return field, _ncc(sim, self.dic_experimental)

    def recorded_field(self, geometry: MapGeometry, rotations: Rotation) -> dsp.DisplacementField:
        """The displacement field of the experimental patterns as they are,
        against simulations made as they were: standardised and less their
        mean over the points where the map's mean was divided out of the
        patterns (to first order what the division leaves of faint bands,
        ``(1 + c S_i) / (1 + c mean S) ~ 1 + c (S_i - mean S)``). What the
        patterns themselves determine: the bands :attr:`dic_experimental`
        puts back are nearly noise-free, and standard errors from their
        field missed a domain map's pcx error by 3.7 of them. Only for
        patterns with the map's mean divided out (:attr:`mean_divided`)."""
        sim = self.simulate(geometry, rotations)
        z = ori.standardise(sim.reshape(len(sim), -1))
        sim = (z - z.mean(axis=0)).reshape(sim.shape).astype(np.float32)
        # Unbinned: binned, the standard errors doubled (1.2-2.2e-3 against
        # errors of 1-5e-4)
        return _measure(sim, self.experimental, {**self.dic_kwargs, "binning": 1})

    def measure(self, geometry: MapGeometry, rotations: Rotation) -> dsp.DisplacementField:
        return self.compare(geometry, rotations)[0]

    def ncc(self, geometry: MapGeometry, rotations: Rotation) -> np.ndarray:
        """NCC (N,) of the patterns simulated at *geometry* with the
        experimental ones (:attr:`dic_experimental`), full resolution."""
        sim = self.simulate(geometry, rotations).astype(np.float32)
        return _ncc(sim, self.dic_experimental)

    def refine_orientations(
        self, geometry: MapGeometry, rotations: Rotation, binning: int | None = None
    ) -> tuple[Rotation, np.ndarray]:
        """Refine orientations with kikuchipy, on patterns binned by
        *binning* (default :attr:`loop_binning`)."""
        if self.multi_phase:
            ask = lambda sub, r: sub.refine_orientations(geometry, r, binning)  # noqa: E731
            return _by_phase(self, ask, rotations)
        kw = dict(self.refine_kwargs)
        if self.pseudo_symmetry_ops is not None:
            kw["pseudo_symmetry_ops"] = self.pseudo_symmetry_ops
        ref = refine_orientations(
            self.experimental,
            rotations,
            geometry.detector(self.points),
            self.master_pattern,
            self.energy,
            self.phase,
            self.loop_binning if binning is None else binning,
            **kw,
        )
        return ref.rotations, ref.scores

    @property
    def loop_binning(self) -> int:
        """Binning of the orientation refinements inside the paper's loop
        (:func:`_binning`); the final orientations use full resolution."""
        return _binning(self.experimental.shape[1:])

    def operators(self) -> Rotation:
        """Identity followed by the pseudo-symmetry operators."""
        ops = Rotation.identity(1)
        if self.pseudo_symmetry_ops is not None:
            ops = Rotation(np.concatenate([ops.data, self.pseudo_symmetry_ops.flatten().data]))
        return ops

    def variants(self, rotations: Rotation) -> tuple[np.ndarray, Rotation]:
        """Return, per point, the pseudo-symmetry operator (0: none) that
        brings the start closest to *rotations*, and the remaining
        deviation ``~(op * start) * rotation`` (a sample-frame rotation);
        with several phases, each phase's operators."""
        if self.multi_phase:
            return _by_phase(self, lambda sub, r: sub.variants(r), rotations)
        ops_all = self.operators()
        angles = np.stack(
            [(~(op * self.start_rotations) * rotations).angle for op in ops_all], axis=1
        )
        k = np.argmin(angles, axis=1)
        return k, ~(ops_all[k] * self.start_rotations) * rotations

    def rotation_offsets(self, rotations: Rotation) -> np.ndarray:
        """Rotation vectors (N, 3) of *rotations* away from the start (its
        closest variant), or with the crystal model from the parent they
        share (in their variants): the offsets of the orientation prior."""
        if self.crystal is not None:
            return self.crystal.deviations(rotations)[1]
        return rotation_vectors(self.variants(rotations)[1])

    def refined_ncc(self, geometry: MapGeometry, rotations: Rotation) -> np.ndarray:
        """NCC (N,) of the patterns with their simulations after the
        *rotations* are refined at *geometry* (Gauss-Newton, coarse to
        fine, :func:`~kikuchipy_geomdic.indexing.orientation.refine_arrays`)."""
        if self.multi_phase:
            return _by_phase(self, lambda sub, r: sub.refined_ncc(geometry, r), rotations)
        det = geometry.detector(self.points)
        pcs = np.broadcast_to(det.pc.reshape(-1, 3), (rotations.size, 3))
        return ori.refine_arrays(
            self.experimental,
            rotations.data.reshape(-1, 4),
            pcs,
            ori.detector_matrix(det),
            self.arrays,
        ).scores

    def best_variants(self, geometry: MapGeometry, rotations: Rotation) -> Rotation:
        """Return per point the variant ``op * rotation`` its pattern shows.

        The candidates are refined at *geometry* and compared as
        :func:`~kikuchipy_geomdic.indexing.reindex.reindex` does (its
        per-point refinement, full resolution only): the best of them
        refined to convergence, the others started at its variants and
        given a fixed number of steps, then
        :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants`.
        Unrefined, a right variant a few tenths of a degree off lost to a
        wrong one refined by the loop (measured with the de-ebsd BaTiO3
        master pattern: 6 of 36 points kept a wrong variant). Each
        refined to convergence from its own start, and asked again where
        it had answered, the same choices took over half of a domain map's
        calibration (tutorial 03's map, seeds 0-2: 42.6, 23.1 and 38.4 s
        against 17.9, 14.5 and 24.7 s). With several phases, each phase's
        points with its own operators."""
        if self.multi_phase:
            return _best_variants(self, geometry, rotations)
        ops = self.operators()
        if ops.size == 1:
            return rotations
        chosen = self._variant_choices.get((geometry, rotations.data.tobytes()))
        if chosen is not None:
            return chosen
        det = geometry.detector(self.points)
        pcs = det.pc.reshape(-1, 3)
        pcs = np.repeat(pcs, rotations.size, axis=0) if pcs.shape[0] == 1 else pcs
        rows = _refine_points(
            self.experimental,
            rotations.data.reshape(-1, 4),
            pcs,
            self.arrays,
            ori.detector_matrix(det),
            levels=(1,),
            max_step=ori.MAX_STEP,
            dic_rms=False,
            ops=ops[1:].data,
        )
        k = rows[:, _VARIANT].astype(np.int64)
        # The rotations themselves where nothing changes, not their product
        # with the identity (orix normalises it to within 1e-16): the DIC
        # stage, seeing a change, chose the variants again in the basin
        # until its iterations ran out (8 of 36 domain maps "not converged")
        chosen = ops[k] * rotations if k.any() else rotations
        # Chosen at a geometry, the variants stand there: asked again from
        # the same rotations or from those chosen (the DIC stage's last
        # question is the full field's first), the answer is this one
        for asked in (rotations, chosen):
            self._variant_choices[(geometry, asked.data.tobytes())] = chosen
        return chosen

    @cached_property
    def _variant_choices(self) -> dict:
        """:meth:`best_variants`' answers by geometry and rotations."""
        return {}

    def jacobian(
        self, geometry: MapGeometry, rotations: Rotation, field0: dsp.DisplacementField, kind: str
    ) -> np.ndarray:
        if kind == "finite-difference":
            return finite_difference_jacobian(
                lambda g: self.measure(g, rotations).residual,
                geometry,
                self.parameters,
                self.steps,
            )
        return analytic_jacobian(
            geometry, self.points, field0.positions, field0.counts, self.parameters, self.steps
        )


def _binning(shape: tuple[int, int]) -> int:
    """The largest factor dividing the pattern *shape* that keeps at least
    :data:`LOOP_MIN_SIZE` px a side."""
    ny, nx = shape
    b = 1
    for f in range(2, min(ny, nx) // LOOP_MIN_SIZE + 1):
        if ny % f == 0 and nx % f == 0:
            b = f
    return b


def _measure(sim: np.ndarray, experimental: np.ndarray, kwargs: Mapping) -> dsp.DisplacementField:
    """The displacement field of *experimental* against *sim*; ROIs without
    a vector are not warned about here: the same ROIs come up at every step
    of a calibration, and the driver names them once, from its last field."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=dsp.EMPTY_ROIS_WARNING)
        return dsp.measure_displacements(sim, experimental, **kwargs)


@dataclass(frozen=True)
class _State:
    """A geometry and orientations, with the displacement field and the
    NCC (N,) of the patterns simulated there against the experimental ones."""

    geometry: MapGeometry
    rotations: Rotation
    field: dsp.DisplacementField
    scores: np.ndarray

    @classmethod
    def measure(cls, problem: _Problem, geometry: MapGeometry, rotations: Rotation) -> _State:
        """The state at *geometry* and *rotations*, from one simulation."""
        fld, scores = problem.compare(geometry, rotations)
        return cls(geometry=geometry, rotations=rotations, field=fld, scores=scores)


@dataclass(frozen=True)
class _LoopOutcome:
    """What a loop returns: the final state, one history record per trial
    step, whether it converged, the field at the start and whether the
    state's variants were found each point's best at its geometry."""

    state: _State
    history: list[dict[str, Any]]
    converged: bool
    field_before: dsp.DisplacementField
    variants_best: bool = False


def _step_record(
    it, names, geometry, ncc_before, ncc_after, before, after, damping, accepted, **extra
) -> dict[str, Any]:
    """One entry of :attr:`GeometryRefinementResult.history`."""
    return dict(
        iteration=it,
        parameters=dict(zip(names, map(float, geometry.values(names)))),
        ncc_before=ncc_before,
        ncc_after=ncc_after,
        displacement_before=before,
        displacement_after=after,
        damping=damping,
        accepted=accepted,
        **extra,
    )
