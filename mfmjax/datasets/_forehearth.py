r"""A simulated glass forehearth (last zone), the paper's case study (`method.md` section 9).

The plant data of the paper are private; this is a physically based stand-in.

**Glass.** 1-D advection-dispersion of the glass temperature $T(x, t)$ along the zone,
finite volumes (upwind advection, central dispersion, Crank-Nicolson in time):

$$\partial_t T + v\,\partial_x T = D\,\partial_{xx} T
  + \frac{q_{crown}(t) - U\,(T - T_{amb})}{\rho c_p d}$$

- $v = \dot m / (\rho W d) + v_{conv}$: the mean flow from the glass pull rate $\dot m$ plus a
  constant free-convection drift of the hot surface layer (where the thermocouples are), so the
  transport delay of input 1, $x_{tc}/v$, is 265 s at 82 t/24h, 319 s at 60 and 335 s at 55
  (the paper: 260-319 s and 313-337 s).
- $D$: Taylor-Aris axial dispersion from the vertical velocity profile (much larger than the
  radiative conductivity of molten glass).
- $q_{crown}$: heat from the burners through the crown refractory, a first-order lag of the
  burner power, which grows with the square root of the gas-air mixture pressure (orifice flow).
- Inlet: $T(0, t)$ = the previous zone's temperature (input 1); outlet: zero gradient.

**Measurements.** The zone thermocouple (output) sits near the zone end, with a first-order
sensor lag; all measurements carry white noise. Input 2 (mixture pressure) is set by the zone's
PI temperature controller (detuned, with set-point changes); input 1 follows the previous zone's
set-point changes with its own lag plus a slow random drift. The pull rate (the unmeasured
disturbance) steps and ramps down between operating points; it is returned for plots only.
Sampling: 1 s. Deterministic per seed.
"""

from __future__ import annotations

import numpy as np

from .. import _boundary as _b

# -- physical constants (SI unless stated) ----------------------------------------------------
RHO = 2450.0  # kg/m^3, density of molten soda-lime glass at ~1150 degC
CP = 1300.0  # J/(kg K), specific heat of molten soda-lime glass
WIDTH = 0.63  # m, channel width
DEPTH = 0.135  # m, glass depth
LENGTH = 2.0  # m, length of the last zone
X_TC = 1.9  # m, zone thermocouple position (near the zone end), from the inlet thermocouple
V_CONV = 2.6197e-3  # m/s, free-convection drift of the surface layer (independent of pull)
DISPERSION = 2.0e-4  # m^2/s, Taylor-Aris axial dispersion (velocity profile across the depth)
U_LOSS = 30.0  # W/(m^2 K), heat loss through walls, bottom and crown per glass surface area
T_AMB = 40.0  # degC, surroundings of the channel
Q_NOM = 20.0e3  # W/m^2, burner heat flux into the glass at the nominal pressure
P_NOM = 10.0  # mbar, nominal gas-air mixture pressure
P_MIN, P_MAX = 1.0, 30.0  # mbar, pressure limits of the burner valve
TAU_CROWN = 400.0  # s, thermal lag of the crown refractory between flame and glass
TAU_TC = 20.0  # s, thermocouple (sheathed, in the glass) lag
TAU_PREV = 300.0  # s, closed-loop response of the previous zone to its set-point
NOISE_TC = 0.05  # degC, thermocouple noise (standard deviation)
NOISE_P = 0.02  # mbar, pressure transmitter noise
CELLS = 100  # finite volumes along the zone (dx = 2 cm)
SUBSTEPS = 2  # Crank-Nicolson steps per 1 s sample
KP, TI = 0.4, 900.0  # PI controller: mbar per degC, integral time in s (detuned, slow moves)
T_PER_DAY = 1000.0 / 86400.0  # kg/s per t/24h


def transport_delay(pull):
    """Transport delay (s) from the inlet thermocouple to the zone thermocouple at `pull` t/24h."""
    pull = _b.array("transport_delay", "pull", pull, ndim=(0, 1))
    if np.any(pull <= 0):
        raise ValueError(f"transport_delay(): pull must be > 0 t/24h (got {pull.tolist()})")
    return X_TC / _velocity(pull)


def _velocity(pull):
    return pull * T_PER_DAY / (RHO * WIDTH * DEPTH) + V_CONV


# -- experiments: schedules of the pull rate and of the set-points -----------------------------
# (time s, value) breakpoints, linear in between; "steps" are 120 s ramps (job changes).
_EXPERIMENTS = {
    1: {
        "duration": 8000,
        "pull": [(0, 82), (1400, 82), (1520, 76), (3300, 76), (3420, 70), (4300, 70),
                 (4420, 64), (5800, 64), (5920, 60), (8000, 60)],
        "prev_sp": [(0, 1172), (2000, 1172), (2001, 1175), (4900, 1175), (4901, 1171),
                    (6600, 1171), (6601, 1173), (8000, 1173)],
        "zone_sp": [(0, 1164), (2600, 1164), (2601, 1162), (5200, 1162), (5201, 1165),
                    (7000, 1165), (7001, 1163), (8000, 1163)],
    },
    2: {
        "duration": 9500,
        "pull": [(0, 62), (2200, 62), (2320, 59), (4300, 59), (4420, 57), (6500, 57),
                 (6620, 55), (9500, 55)],
        "prev_sp": [(0, 1168), (1500, 1168), (1501, 1171), (5000, 1171), (5001, 1167),
                    (7800, 1167), (7801, 1170), (9500, 1170)],
        "zone_sp": [(0, 1160), (3100, 1160), (3101, 1163), (6000, 1163), (6001, 1160),
                    (8400, 1160), (8401, 1162), (9500, 1162)],
    },
}


def _schedule(points, t):
    tp, vp = zip(*points)
    return np.interp(t, tp, vp)


def _operator(v: float, dx: float, h: float):
    """Banded (I - h/2 L) and the explicit (I + h/2 L) of the cell operator L at velocity v."""
    n = CELLS
    k_loss = U_LOSS / (RHO * CP * DEPTH)
    lower = v / dx + DISPERSION / dx**2  # coupling to the upstream cell
    upper = DISPERSION / dx**2  # coupling to the downstream cell
    diag = -(v / dx + 2 * DISPERSION / dx**2 + k_loss) * np.ones(n)
    diag[-1] += upper  # zero gradient at the outlet: the ghost cell equals the last cell
    ab = np.zeros((3, n))
    ab[0, 1:] = -h / 2 * upper
    ab[1] = 1 - h / 2 * diag
    ab[2, :-1] = -h / 2 * lower
    return ab, (lower, upper, diag)


def _apply(L, T):
    lower, upper, diag = L
    out = diag * T
    out[1:] += lower * T[:-1]
    out[:-1] += upper * T[1:]
    return out


def forehearth(experiment: int = 1, seed: int = 0) -> dict:
    """Simulate experiment 1 (pull 82 -> 60 t/24h, 8000 s) or 2 (62 -> 55 t/24h, 9500 s).

    **Returns:** a dict of 1 s samples: `t` (s), `y` (zone temperature, degC, measured),
    `u` ((T, 2): previous zone temperature degC, gas-air mixture pressure mbar, measured),
    `pull` (t/24h, not measured), `delay` (transport delay of input 1, s), `names`, `units`,
    `intersample` (input 1 foh: a temperature; input 2 zoh: a controller output held between
    samples).
    """
    if isinstance(experiment, bool) or experiment not in _EXPERIMENTS:
        raise ValueError(f"forehearth(): experiment must be 1 or 2 (got {experiment!r})")
    seed = _b.integer("forehearth", "seed", seed, lo=0)
    from scipy.linalg import solve_banded  # here: `import mfmjax` does not load scipy.linalg

    ex = _EXPERIMENTS[experiment]
    rng = np.random.default_rng(seed)
    n_samples = ex["duration"] + 1
    t = np.arange(n_samples, dtype=np.float64)
    pull = _schedule(ex["pull"], t)
    prev_sp = _schedule(ex["prev_sp"], t)
    zone_sp = _schedule(ex["zone_sp"], t)
    # previous zone: its set-point through a first-order loop plus a slow random drift
    t_in = np.empty(n_samples)
    t_in[0] = loop = prev_sp[0]
    drift, lag = 0.0, np.exp(-1.0 / TAU_PREV)
    w = rng.standard_normal(n_samples) * 0.02
    for k in range(1, n_samples):
        loop = prev_sp[k - 1] + (loop - prev_sp[k - 1]) * lag
        drift = drift * (1 - 1 / 600) + w[k]  # ~0.3 degC wander over ~10 min
        t_in[k] = loop + drift
    dx = LENGTH / CELLS
    x = (np.arange(CELLS) + 0.5) * dx
    i_tc = int(np.searchsorted(x, X_TC)) - 1
    frac = (X_TC - x[i_tc]) / dx
    h = 1.0 / SUBSTEPS
    k_loss = U_LOSS / (RHO * CP * DEPTH)
    heat = 1.0 / (RHO * CP * DEPTH)  # degC/s per W/m^2

    def at_tc(T):
        return T[i_tc] * (1 - frac) + T[i_tc + 1] * frac

    def steady(v, q, inlet):
        _, (lower, upper, diag) = _operator(v, dx, h)
        A = np.diag(diag) + np.diag(np.full(CELLS - 1, lower), -1) + np.diag(
            np.full(CELLS - 1, upper), 1)
        rhs = -(q * heat + k_loss * T_AMB) * np.ones(CELLS)
        rhs[0] -= lower * inlet
        return np.linalg.solve(A, rhs)

    # initial steady state: the crown flux (hence pressure) that holds the zone set-point
    v0 = _velocity(pull[0])
    base, unit = steady(v0, 0.0, t_in[0]), steady(v0, 1.0, t_in[0])
    q_crown = (zone_sp[0] - at_tc(base)) / (at_tc(unit) - at_tc(base))
    p = float(np.clip(P_NOM * (max(q_crown, 0.0) / Q_NOM) ** 2, P_MIN, P_MAX))
    T = base + q_crown * (unit - base)
    tc = at_tc(T)
    integ = p - P_NOM  # controller integral state: starts in balance
    y = np.empty(n_samples)
    u = np.empty((n_samples, 2))
    cache = {}
    for k in range(n_samples):
        # measurements at sample k; the controller's new pressure is held for 1 s (zoh)
        y[k] = tc + NOISE_TC * rng.standard_normal()
        u[k, 0] = t_in[k] + NOISE_TC * rng.standard_normal()
        err = zone_sp[k] - y[k]
        integ += KP * err / TI
        p = float(np.clip(P_NOM + integ + KP * err, P_MIN, P_MAX))
        u[k, 1] = p + NOISE_P * rng.standard_normal()
        if k == n_samples - 1:
            break
        v = _velocity(pull[k])
        key = round(v, 12)
        if key not in cache:
            cache = {key: _operator(v, dx, h)}
        ab, L = cache[key]
        q_target = Q_NOM * np.sqrt(p / P_NOM)
        for s in range(SUBSTEPS):
            a = (s + 0.5) / SUBSTEPS  # inlet temperature mid-substep (linear between samples)
            inlet = (1 - a) * t_in[k] + a * t_in[k + 1]
            q_crown += (q_target - q_crown) * (1 - np.exp(-h / TAU_CROWN))
            src = (q_crown * heat + k_loss * T_AMB) * np.ones(CELLS)
            src[0] += (v / dx + DISPERSION / dx**2) * inlet
            T = solve_banded((1, 1), ab, T + h / 2 * _apply(L, T) + h * src)
            tc += (at_tc(T) - tc) * (1 - np.exp(-h / TAU_TC))
    return {
        "t": t, "y": y, "u": u, "pull": pull, "delay": transport_delay(pull),
        "names": ("zone_temperature", "previous_zone_temperature", "mixture_pressure"),
        "units": ("degC", "degC", "mbar"), "intersample": ("foh", "zoh"),
        "experiment": experiment, "seed": seed,
    }
