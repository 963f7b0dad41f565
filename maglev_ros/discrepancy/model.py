"""The twin as the discrepancy core runs it: calibrated scales + physics extensions, by composition.

``ModelSpec`` = nominal ``TwinConfig`` and line + calibrated scale factors (E, kb, kp, kv) +
extension parameters. :func:`predict` runs the coupled twin (``coupling.TwinStepper``) along the
recorded vehicle position/speed and returns each measured channel's prediction on its own time
stamps. Extensions that need a hook inside the twin are built here from the twin's public
pieces, without changing the twin files:

- per-end bearing stiffness and damaged girder zones: :func:`maglev_ros.twin.guideway.assemble_span`
  with ``kb_ends`` (one stiffness per end) and ``ei_factors`` (one EI factor per element) replaces
  the span FE models of the stepper's ``Guideway``;
- car-body bending: :func:`flexible_vehicle` adds one free-free bending DOF of the car body to the
  twin's assembled rigid 18-DOF ``VehicleModel`` (secondary springs see psi(x) eta);
- control delay, two forms: a transport delay (the law acts on measurements tau old: sampling,
  filters, bus; ``LevitationDesign.control_delay_s``, a (2,2) Pade all-pass in the twin) and a
  first-order lag of the current behind the law (``coil_inductance_h = tau R``: the coil's own
  time constant); they agree to O((w tau)^2) at the levitation frequencies and differ above
  1/(2 pi tau), where the lag attenuates and the delay only turns the phase;
- magnet nonlinearity: smooth current saturation I0 + L tanh((I - I0)/L) in the twin's force
  kernel (``TwinStepper(current_limit_a=L)``, :mod:`maglev_ros.twin.coupling`);
- nonlinear air springs (discovery): a force law f(d, d_rate) per secondary air spring, added by
  operator splitting around the stepper (:mod:`maglev_ros.twin.spring_force`);
- sensor errors (scale, offset, drift) act on the predicted channel after the simulation;
- stochastic additions (ambient excitation) act on band powers (see :mod:`.features`).
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any, Callable, Mapping

import numpy as np

from maglev_ros.twin.coupling import PassResult, TwinStepper
from maglev_ros.twin.design import SpanSpec, TwinConfig, line_spans, twin_config_from_metadata, with_levitation
from maglev_ros.twin.guideway import assemble_span
from maglev_ros.twin.levitation import VehicleSystem, LevitationModel, closed_loop
from maglev_ros.twin.spring_force import advance_with_spring_force
from maglev_ros.twin.trajectory import MeasuredTrajectory, drive
from maglev_ros.twin.vehicle import VehicleModel, static_equilibrium, vehicle_from_design

from .attachment import attached_modal
from .recording import Recording

# calibrated (log-scale factors). The girders' density beside E: a displacement sensor sees the static
# deflection (EI) and every sensor the modal frequencies (EI/m), so both are determined; with E alone,
# a 14 % heavier girder than designed left the midspan displacement 11 % off and was called a sensor fault
CAL_PARAMS = ("E", "kb", "kp", "kv", "rho")
CAL_NAMES = {"E": "youngs_modulus_pa", "kb": "bearing_stiffness_n_per_m", "kp": "kp_a_per_m",
             "kv": "kv_a_s_per_m", "rho": "density_kg_m3"}


@dataclass(frozen=True)
class ModelSpec:
    """Nominal twin + calibrated log-scales + extensions (all hashable, so predictions cache)."""
    config: TwinConfig
    spans: tuple[SpanSpec, ...]
    cal: tuple[float, ...] = (0.0,) * len(CAL_PARAMS)      # ln factors of CAL_PARAMS
    span_e_factor: tuple[float, ...] = ()                   # per span (girder_stiffness_loss)
    bearing_factor: tuple[tuple[float, float], ...] = ()    # per span (left, right) kb factors
    # damaged zones: (span index, start, end from the span's start [m], EI factor) (girder_stiffness_loss)
    girder_zones: tuple[tuple[int, float, float, float], ...] = ()
    control_lag_s: float = 0.0                              # first-order lag of the current [s]
    control_delay_s: float = 0.0                            # transport delay of the control law [s]
    carbody_bend_hz: float | None = None
    carbody_zeta: float = 0.02
    current_limit_a: float | None = None                    # saturation L [A] (magnet_nonlinearity)
    current_limit_sides: str = "both"                       # "both" or "upper" (twin.coupling)
    resonator: Any = None                                   # discovery: added girder resonator (.attachment.Resonator)
    sensor_error: tuple[tuple[str, float, float, float], ...] = ()   # (channel, scale, offset, drift/s)
    # channels of sensor_error whose offset and drift are re-estimated on each recording (an
    # accelerometer's bias is not repeatable between recordings: it changes at power-up and with
    # temperature); their entry's offset and drift are then those of the pass it was fitted on
    sensor_rezeroed: tuple[str, ...] = ()
    ambient_log10_psd: float | None = None                  # modal force PSD at 20 Hz (ambient_excitation)
    ambient_slope: float = 0.0                              # PSD ~ (f / 20 Hz)^slope
    # (channel, band powers): a background measured on the quiet stretches of a pass; then
    # ambient_log10_psd is the log10 factor on it and the slope is unused (ambient_excitation.measured)
    ambient_background: tuple[tuple[str, tuple[float, ...]], ...] = ()
    dropouts: tuple[tuple[str, float, float, float], ...] = ()  # (channel, t0_s, t1_s, value held)
    air_spring_force: tuple[tuple[str, float], ...] = ()    # (term of AIR_SPRING_TERMS, coefficient SI) per air spring
    dt_max_s: float | None = None
    # Rayleigh damping ratio on modes 1-2 of every span as measured (calibrate stage); None: the design's
    guideway_damping_ratio: float | None = None

    def with_(self, **kw) -> "ModelSpec":
        return replace(self, **kw)

    def physics_only(self) -> "ModelSpec":
        """Without what is added to the simulated signals (sensor errors, ambient vibration, dropouts):
        the part a simulation depends on (a cache key)."""
        return replace(self, sensor_error=(), sensor_rezeroed=(), ambient_log10_psd=None, ambient_slope=0.0,
                       ambient_background=(), dropouts=())

    # --- calibrated values ---------------------------------------------------------------
    def cal_factor(self, name: str) -> float:
        k = CAL_PARAMS.index(name)
        return math.exp(self.cal[k]) if k < len(self.cal) else 1.0

    def calibrated_values(self) -> dict:
        g, lev = self.config.guideway, self.config.levitation
        return {"youngs_modulus_pa": g.youngs_modulus_pa * self.cal_factor("E"),
                "bearing_stiffness_n_per_m": g.bearing_stiffness_n_per_m * self.cal_factor("kb"),
                "kp_a_per_m": lev.kp_a_per_m * self.cal_factor("kp"),
                "kv_a_s_per_m": lev.kv_a_s_per_m * self.cal_factor("kv"),
                "density_kg_m3": g.density_kg_m3 * self.cal_factor("rho")}

    def effective_spans(self) -> tuple[SpanSpec, ...]:
        fe, fk, fr = self.cal_factor("E"), self.cal_factor("kb"), self.cal_factor("rho")
        out = []
        for i, s in enumerate(self.spans):
            e = fe * (self.span_e_factor[i] if i < len(self.span_e_factor) else 1.0)
            p = replace(s.props, youngs_modulus_pa=s.props.youngs_modulus_pa * e,
                        bearing_stiffness_n_per_m=s.props.bearing_stiffness_n_per_m * fk,
                        density_kg_m3=s.props.density_kg_m3 * fr)
            if self.guideway_damping_ratio is not None:
                p = replace(p, damping_ratio=float(self.guideway_damping_ratio))
            out.append(replace(s, props=p))
        return tuple(out)

    def effective_config(self) -> TwinConfig:
        lev = self.config.levitation
        cfg = with_levitation(self.config, kp_a_per_m=lev.kp_a_per_m * self.cal_factor("kp"),
                              kv_a_s_per_m=lev.kv_a_s_per_m * self.cal_factor("kv"))
        if self.control_lag_s > 0:
            cfg = with_levitation(cfg, coil_inductance_h=self.control_lag_s * cfg.levitation.coil_resistance_ohm)
        if self.control_delay_s > 0:
            cfg = with_levitation(cfg, control_delay_s=float(self.control_delay_s))
        if self.dt_max_s is not None:
            cfg = replace(cfg, numerics=replace(cfg.numerics, dt_max_s=self.dt_max_s))
        return cfg


def base_spec(metadata: Mapping, n_elements: int | None = None) -> ModelSpec:
    """Nominal twin from the recording's design block (defaults where absent) and line."""
    cfg = twin_config_from_metadata(metadata)
    if n_elements is not None:
        cfg = replace(cfg, numerics=replace(cfg.numerics, n_elements_per_span=int(n_elements)))
    spans = line_spans(metadata.get("line"), cfg)
    return ModelSpec(cfg, spans)


# ------------------------------------------------------------------------------------------
def _free_free_shape(L: float):
    bl = 4.730040745
    sig = (math.cosh(bl) - math.cos(bl)) / (math.sinh(bl) - math.sin(bl))

    def psi(x):
        b = bl * np.clip(np.asarray(x, dtype=float), 0.0, L) / L
        return 0.5 * (np.cosh(b) + np.cos(b) - sig * (np.sinh(b) + np.sin(b)))   # 1 at the ends
    return psi


def _carbody_beam(model: VehicleModel):
    """(x_start, psi, length) of the car body taken as a uniform free-free beam over the secondary spring
    positions plus 15 % overhang each end; psi(x - x_start) is its first bending shape."""
    xs = [c.x_m for c in model.connections if c.body_b == "car" or c.body_a == "car"]
    span = max(xs) - min(xs)
    L = 1.3 * span if span > 0 else 25.0
    return 0.5 * (max(xs) + min(xs)) - L / 2, _free_free_shape(L), L


def body_point_row(model: VehicleModel, x_m: float) -> np.ndarray:
    """Row mapping the vehicle DOFs to the vertical motion of the car-body point at ``x_m``
    (relative to the vehicle reference point): heave + pitch, plus the bending DOF ``car.bend``
    of a :func:`flexible_vehicle`."""
    row = model.point_row("car", x_m)
    if "car.bend" in model.dof_names:
        x_start, psi, _ = _carbody_beam(model)
        row = row.copy()
        row[model.dof_names.index("car.bend")] = float(psi(x_m - x_start))
    return row


def flexible_vehicle(model: VehicleModel, bend_hz: float, zeta: float = 0.02) -> VehicleModel:
    """Add the first free-free bending mode of the car body (uniform beam over the secondary
    spring positions plus 15 % overhang each end) as DOF ``car.bend``, shape 1 at the body ends,
    generalised mass from the uniform mass distribution (= m/4)."""
    car = next(b for b in model.bodies if b.name == "car")
    x_start, psi, L = _carbody_beam(model)
    grid = np.linspace(0, L, 401)
    mb = car.mass_kg * float(np.trapezoid(psi(grid) ** 2, grid)) / L
    wb = 2 * math.pi * bend_hz
    n = model.n_dof
    M = np.zeros((n + 1, n + 1)); C = np.zeros_like(M); K = np.zeros_like(M)
    M[:n, :n], C[:n, :n], K[:n, :n] = model.mass, model.damping, model.stiffness
    M[n, n] = mb
    K[n, n] = mb * wb ** 2
    C[n, n] = 2 * zeta * mb * wb
    for c in model.connections:
        if "car" not in (c.body_a, c.body_b):
            continue
        t = model.point_row(c.body_a, c.x_m) - model.point_row(c.body_b, c.x_m)
        sgn = 1.0 if c.body_a == "car" else -1.0
        tf = np.append(t, sgn * float(psi(c.x_m - x_start)))
        K += c.stiffness_n_per_m * (np.outer(tf, tf) - np.pad(np.outer(t, t), (0, 1)))
        C += c.damping_n_s_per_m * (np.outer(tf, tf) - np.pad(np.outer(t, t), (0, 1)))
    B = np.vstack([model.magnet_input, np.zeros((1, model.n_magnets))])
    g = np.append(model.gravity_load_n, 0.0)
    return VehicleModel(model.bodies, model.connections, model.magnets, model.dof_names + ("car.bend",),
                        M, C, K, B, g)


def build_stepper(spec: ModelSpec, sensors: Mapping[str, float], *, fs_out_hz: float,
                  start_position_m: float, start_speed_mps: float, t0_s: float,
                  irregularity=None) -> TwinStepper:
    cfg = spec.effective_config()
    st = TwinStepper(cfg, spec.effective_spans(), sensors=dict(sensors), irregularity=irregularity,
                     fs_out_hz=fs_out_hz, start_position_m=start_position_m, start_speed_mps=start_speed_mps,
                     t0_s=t0_s, init="rest", current_limit_a=spec.current_limit_a,
                     current_limit_sides=spec.current_limit_sides)
    st = stepper_customizer(spec)(st)
    st._init_static()
    return st


def stepper_customizer(spec: ModelSpec) -> Callable[[TwinStepper], TwinStepper]:
    """What a plain ``TwinStepper`` of the spec's config and spans lacks, installed on one before it
    is initialised: spans with their own bearings or damaged zones, an attached resonator, car-body
    bending, the current limit. Handed to the rail reconstruction too, so that the girder
    deflection it removes is the one this twin adds (a damaged zone left out there put its girder's
    vibration into the rail: the twin with a case's true zone then missed 40 % of that span's
    first-mode response)."""
    def customize(st: TwinStepper) -> TwinStepper:
        cfg = spec.effective_config()
        changed = False
        own = _own_span_fes(spec, spec.effective_spans(), cfg.numerics.n_elements_per_span)
        if own:
            st.guideway.spans_fe = tuple(own.get(i, fe) for i, fe in enumerate(st.guideway.spans_fe))
            st.modal = st.guideway.modes(cfg.numerics.mode_cutoff_hz, cfg.numerics.min_modes_per_span)
            st.sensor_shapes = st.modal.shapes_at(st.sensor_x_m) if st.sensor_x_m.size else np.zeros((0, st.modal.n_modes))
            changed = True
        if spec.resonator is not None:
            st.modal = attached_modal(guideway_modal(spec.with_(resonator=None)), spec.resonator,
                                      cfg.numerics.mode_cutoff_hz, cfg.numerics.min_modes_per_span)
            st.sensor_shapes = st.modal.shapes_at(st.sensor_x_m) if st.sensor_x_m.size else np.zeros((0, st.modal.n_modes))
            changed = True
        if spec.carbody_bend_hz is not None:
            vm = flexible_vehicle(st.vehicle.model, spec.carbody_bend_hz, spec.carbody_zeta)
            eq = static_equilibrium(vm)
            lev = LevitationModel.from_design(cfg.levitation, eq.magnet_force_n)
            st.vehicle = VehicleSystem(vm, eq, lev, closed_loop(vm, lev))
            changed = True
        if spec.current_limit_a is not None:
            st.current_limit_a = float(spec.current_limit_a)
            st.current_limit_sides = spec.current_limit_sides
        if changed:
            st._setup_matrices()
            st._x = np.zeros(st._nx)
            st._u = np.zeros(3 * st._m)
            nq = st.modal.n_modes
            st._q, st._qd, st._qdd = np.zeros(nq), np.zeros(nq), np.zeros(nq)
            st._F = st.vehicle.levitation.static_force_n.copy()
        return st
    return customize


def guideway_modal(spec: ModelSpec):
    """Modal basis of the spec's guideway (with per-end bearings), for stochastic extensions."""
    from maglev_ros.twin.guideway import Guideway
    cfg = spec.effective_config()
    spans = spec.effective_spans()
    gw = Guideway(spans, cfg.numerics.n_elements_per_span)
    own = _own_span_fes(spec, spans, cfg.numerics.n_elements_per_span)
    if own:
        gw.spans_fe = tuple(own.get(i, fe) for i, fe in enumerate(gw.spans_fe))
    return gw.modes(cfg.numerics.mode_cutoff_hz, cfg.numerics.min_modes_per_span)


def zone_element_factors(length_m: float, n_elements: int, zones) -> np.ndarray:
    """EI factor per element of a span with damaged ``zones`` ((start, end) from the span's start
    [m], EI factor): an element partly in a zone gets the factor in proportion to its overlap."""
    le = length_m / n_elements
    lo, hi = np.arange(n_elements) * le, (np.arange(n_elements) + 1) * le
    f = np.ones(n_elements)
    for x0, x1, fac in zones:
        share = np.clip(np.minimum(hi, x1) - np.maximum(lo, x0), 0.0, None) / le
        f *= 1.0 - share * (1.0 - fac)
    return f


def _own_span_fes(spec: ModelSpec, spans, n_elements: int) -> dict:
    """Span index -> FE model of the spans whose bearings or damaged zones differ from the line's."""
    out = {}
    for i, sp in enumerate(spans):
        fl, fr = spec.bearing_factor[i] if i < len(spec.bearing_factor) else (1.0, 1.0)
        zones = [(x0, x1, f) for j, x0, x1, f in spec.girder_zones if j == i]
        if (fl, fr) == (1.0, 1.0) and not zones:
            continue
        kb = sp.props.bearing_stiffness_n_per_m
        out[i] = assemble_span(sp, n_elements, kb_ends=(kb * fl, kb * fr),
                               ei_factors=zone_element_factors(sp.length_m, n_elements, zones) if zones else None)
    return out


# terms of a force per air spring, as functions of its deflection d [m] (> 0 compresses it) and rate
AIR_SPRING_TERMS = {"d": lambda d, v: d, "d_rate": lambda d, v: v, "d^3": lambda d, v: d ** 3,
                    "d^2": lambda d, v: d ** 2, "d_rate*|d_rate|": lambda d, v: v * np.abs(v)}


def _air_springs(model: VehicleModel) -> list:
    """The secondary air springs of a vehicle model (its connections named ``secondary<k>``)."""
    return [c for c in model.connections if c.name.startswith("secondary")]


def air_spring_rows(model: VehicleModel) -> np.ndarray:
    """(n_springs, n_dof) rows T of the secondary air springs: d = T z (frame point minus car point)."""
    sec = _air_springs(model)
    return np.stack([model.point_row(c.body_a, c.x_m) - model.point_row(c.body_b, c.x_m) for c in sec]) \
        if sec else np.zeros((0, model.n_dof))


def air_spring_force_law(terms) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """f(d, d_rate) = sum of coefficient x term over ``terms`` ((name, coefficient) pairs)."""
    terms = tuple(terms)

    def force(d, d_rate):
        return sum(c * AIR_SPRING_TERMS[k](d, d_rate) for k, c in terms) + 0.0 * d
    return force


# the air-spring force's splitting interval: its error is first order in the interval, here 2 % of
# the period at the 10 Hz top of the band a nonlinear air spring shows in (a fixed time, not per
# output sample: the output rate follows the recording and the twin's step)
AIR_SPRING_SPLIT_S = 2e-3

# simulations by (physics spec, recording, rate), least recently used dropped first: an entry is
# the whole PassResult (~90 columns at the output rate, 18 MB for a 12.7 s pass at 2 kHz), and a
# diagnosis simulates ~240 specs but reuses almost only the last few (keeping them all took 4 GB)
_CACHE: OrderedDict = OrderedDict()
_CACHE_MAX_BYTES = 256 * 2 ** 20


def simulate(spec: ModelSpec, rec: Recording, fs_out_hz: float | None = None) -> PassResult | None:
    """Run the twin along ``rec``'s vehicle position (None for an ambient recording), driven by the
    pass's reconstructed irregularity ``rec.irregularity`` (perfect guideway when None); the twin
    runs ``rec.sensor_delay_s`` behind the stamps (the samples describe the physics that much
    earlier: one delay for all sensor topics, the vehicle accel topic's)."""
    if rec.kind != "pass" or rec.position_time_s is None:
        return None
    phys = spec.physics_only()
    key = (phys, id(rec), fs_out_hz)
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is rec:
        _CACHE.move_to_end(key)
        return hit[1]
    fs = fs_out_hz or max(c.sample_rate_hz for c in rec.channels.values())
    # output every internal step, never coarser than the recording: what lies between a channel's
    # Nyquist and the step's is then removed in predict() as the instrument's anti-alias filter
    # removed it, not folded into the channel's bands (a 500 Hz recording of a girder with modes at
    # 325 and 464 Hz: guideway band misfit 0.16 against 0.09 at 1 kHz, the same twin)
    fs *= max(1, math.ceil((1.0 / fs) / phys.effective_config().numerics.dt_max_s - 1e-9))
    sensors = {n: c.position_m for n, c in rec.channels.items()
               if c.group in ("guideway_accel", "guideway_disp") and c.position_m is not None}
    traj = MeasuredTrajectory.from_samples(rec.position_time_s, rec.position_m, rec.speed_mps)
    tau = float(rec.sensor_delay_s)
    t0 = max(rec.t0_s - tau, float(traj.time_s[0])) - 1.0 / fs
    st = build_stepper(phys, sensors, fs_out_hz=fs, start_position_m=float(traj.position_at(t0)),
                       start_speed_mps=float(traj.speed_at(t0)), t0_s=t0, irregularity=rec.irregularity)
    t_end = rec.t1_s - tau + 1.0 / fs
    step = None
    if spec.air_spring_force:
        rows = air_spring_rows(st.vehicle.model)
        force = air_spring_force_law(spec.air_spring_force)
        every = max(1, int(round(AIR_SPRING_SPLIT_S * fs)))

        def step(s, t, v):
            return advance_with_spring_force(s, t, v, rows, force, every)[0]
    parts = drive(st, traj, t_end, 0.25, step)
    res = PassResult.concat(parts)
    if tau:
        res = replace(res, time_s=res.time_s + tau)
    _CACHE[key] = (rec, res)
    size = sum(_result_bytes(r) for _, r in _CACHE.values())
    while len(_CACHE) > 1 and size > _CACHE_MAX_BYTES:
        size -= _result_bytes(_CACHE.popitem(last=False)[1][1])
    return res


def _result_bytes(res: PassResult) -> int:
    return sum(v.nbytes for v in vars(res).values() if isinstance(v, np.ndarray))


def bias_and_drift(time_s: np.ndarray, residual: np.ndarray) -> tuple[float, float]:
    """Least-squares offset (at the first sample) and drift per second of ``residual``."""
    ok = np.isfinite(residual)
    if ok.sum() < 2:
        return 0.0, 0.0
    t = time_s[ok] - time_s[0]
    d, o = np.polyfit(t, residual[ok], 1)
    return float(o), float(d)


def reference_value(rec: Recording, name: str) -> float:
    """Value a channel reads at rest (gaps: nominal gap; everything else 0)."""
    if rec.channels[name].group == "gap":
        g0 = (rec.metadata.get("vehicle") or {}).get("nominal_gap_m")
        return float(g0) if g0 is not None else 0.010
    return 0.0


def _vehicle_model(spec: ModelSpec) -> VehicleModel:
    """The vehicle model the spec's twin runs (rigid, or with the car-body bending DOF)."""
    vm = vehicle_from_design(spec.config.vehicle)
    return vm if spec.carbody_bend_hz is None else flexible_vehicle(vm, spec.carbody_bend_hz, spec.carbody_zeta)


@lru_cache(maxsize=64)
def _anti_alias_sos(wn: float) -> np.ndarray:
    from scipy import signal
    return signal.butter(12, wn, output="sos")


def anti_aliased(x: np.ndarray, t_s: np.ndarray, fs_channel_hz: float) -> np.ndarray:
    """``x`` (sampled at ``t_s``; (n,) or (n, k) columns) low-passed for a channel sampled at
    ``fs_channel_hz``: zero-phase Butterworth of order 12 at 0.9 x the channel's Nyquist (flat within
    0.3 % below the 0.7 x Nyquist the band features use, :func:`.features.usable_bands`); unchanged
    when x is not finer than the channel. Hand-written: scipy's decimators need an integer rate
    ratio, recordings rarely have one."""
    if x.shape[0] < 64:
        return x
    fs = (x.shape[0] - 1) / float(t_s[-1] - t_s[0])
    if not fs > 1.05 * fs_channel_hz:
        return x
    from scipy import signal
    # the design is cached: a diagnosis filters ~10^4 channel outputs at a handful of rate ratios
    return signal.sosfiltfilt(_anti_alias_sos(round(0.9 * fs_channel_hz / fs, 9)), x, axis=0)


def _twin_source(spec: ModelSpec, res: PassResult, rec: Recording, name: str) -> np.ndarray:
    """The twin output a channel of ``rec`` reads, at the twin's output samples."""
    ch = rec.channels[name]
    if ch.group == "guideway_accel":
        return res.guideway_accel_mps2[:, res.sensor(name)]
    if ch.group == "guideway_disp":
        return res.guideway_disp_m[:, res.sensor(name)]
    if ch.group == "vehicle_accel":
        return res.magnet_accel_mps2[:, ch.magnet - 1]
    if ch.group == "body_accel":
        return res.vehicle_acc_mps2 @ body_point_row(_vehicle_model(spec), ch.body_x_m)
    return res.magnet_gap_m[:, ch.magnet - 1]


# the channels sampled from one simulation, by (simulation, recording): a diagnosis predicts the same
# simulation again and again with other sensor errors (which leave the twin's physics alone)
_SAMPLED: OrderedDict = OrderedDict()
_SAMPLED_MAX = 16


def _sampled(spec: ModelSpec, res: PassResult, rec: Recording) -> dict[str, np.ndarray]:
    key = (id(res), id(rec))
    hit = _SAMPLED.get(key)
    if hit is not None and hit[0] is res and hit[1] is rec:
        _SAMPLED.move_to_end(key)
        return hit[2]
    by_rate: dict[float, list[str]] = {}
    for name, ch in rec.channels.items():
        by_rate.setdefault(float(ch.sample_rate_hz), []).append(name)
    out = {}
    for fs_ch, names in by_rate.items():
        src = np.column_stack([_twin_source(spec, res, rec, n) for n in names])
        src = anti_aliased(src, res.time_s, fs_ch)
        for j, n in enumerate(names):
            out[n] = np.interp(rec.channels[n].time_s, res.time_s, src[:, j])
    _SAMPLED[key] = (res, rec, out)
    while len(_SAMPLED) > _SAMPLED_MAX:
        _SAMPLED.popitem(last=False)
    return out


def predict(spec: ModelSpec, rec: Recording, fs_out_hz: float | None = None) -> dict[str, np.ndarray]:
    """Predicted time series of every channel of ``rec`` (on its time stamps), with sensor errors (a
    re-zeroed channel's offset and drift are the least-squares line of ``rec``'s own residual)."""
    res = simulate(spec, rec, fs_out_hz)
    if res is None:
        out = {name: np.full(ch.time_s.size, reference_value(rec, name)) for name, ch in rec.channels.items()}
    else:
        out = {name: y.copy() for name, y in _sampled(spec, res, rec).items()}
    for (name, s, o, d) in spec.sensor_error:
        if name in out:
            ref = reference_value(rec, name)
            t = rec.channels[name].time_s
            out[name] = ref + s * (out[name] - ref)
            if name in spec.sensor_rezeroed:
                o, d = bias_and_drift(t, rec.channels[name].values - out[name])
            out[name] = out[name] + o + d * (t - t[0])
    for (name, t0, t1, val) in spec.dropouts:
        if name in out:
            t = rec.channels[name].time_s
            sel = (t >= t0) & (t <= t1)
            out[name] = np.where(sel, val, out[name])
    return out
