"""The ranked candidate table of a search."""

from __future__ import annotations

import json
import math

import equinox as eqx
import jax
import numpy as np

from .._model import Model, finite_or_none, plain_number
from .._modulating import ModulatingFunction, as_values
from .._signals import dependent_candidates
from .._status import Status, describe
from .._structure import Structure

E_TIE_RTOL = 1e-12  # E values closer than this fraction of int (y - mean y)^2 rank by
# parameter count (of int y^2 before: an output at a level of 1e5 tied every candidate)


class SearchResult(eqx.Module):
    """Ranked candidates of a `search` (numpy arrays, one row per feasible candidate).

    Columns: `n`, `m` (C, K), `N`, `M`, `h`, `delays` (C, K), `J` (scale-free J_rel), `E`,
    `fit`, `aic`, `bic`, `status`, `theta` (C, p_max; padded layout [a_0..a_nmax, b_1.., ..]),
    `a` (C, nmax+1), `b` (C, K, mmax+1), `offset`. `rank` orders them best first by `score`.
    """

    columns: dict
    rank: np.ndarray
    score: str = eqx.field(static=True)
    n_max: int = eqx.field(static=True)
    m_max: tuple[int, ...] = eqx.field(static=True)
    intersample: tuple[str, ...] = eqx.field(static=True)
    has_offset: bool = eqx.field(static=True)
    output_name: str = eqx.field(static=True)
    input_names: tuple[str, ...] = eqx.field(static=True)
    compile_s: float = eqx.field(static=True)
    run_s: float = eqx.field(static=True)
    identify: tuple | None = eqx.field(static=True, default=None)  # `search`'s identify= windows
    # `search`'s validate= window and observer_window (E, fit, AIC and BIC are of them); refine
    # of this result scores there unless told otherwise
    validate: tuple | None = eqx.field(static=True, default=None)
    observer_window: float | None = eqx.field(static=True, default=None)

    def __len__(self) -> int:
        return int(self.rank.shape[0])

    def row(self, i: int) -> dict:
        """Candidate of rank `i` (0 = best) as a plain dict (`J` is J_rel, `J_raw` the paper's
        J of eq. 8)."""
        from .._boundary import check_rank

        return self._row(check_rank("SearchResult.row", i, len(self)))

    def _row(self, i: int) -> dict:
        c, j = self.columns, int(self.rank[i])
        n = int(c["n"][j])
        m = [int(v) for v in c["m"][j]]
        return {
            "rank": i + 1,
            "n": n,
            "m": m,
            "N": plain_number(c["N"][j]),
            "M": plain_number(c["M"][j]),
            "h": float(c["h"][j]),
            "delays": [float(v) for v in c["delays"][j]],
            "J": finite_or_none(c["J"][j]),
            "J_raw": finite_or_none(c["J_raw"][j]),
            "E": finite_or_none(c["E"][j]),
            "fit": finite_or_none(c["fit"][j]),
            "aic": finite_or_none(c["aic"][j]),
            "bic": finite_or_none(c["bic"][j]),
            "status": describe(int(c["status"][j])),
            "a": [float(v) for v in c["a"][j][: n + 1]],
            "b": [[float(v) for v in c["b"][j][k][: m[k] + 1]] for k in range(len(m))],
            "offset": float(c["offset"][j]) if self.has_offset else None,
        } | ({"E_holdout": finite_or_none(c["E_holdout"][j]),
              "fit_holdout": finite_or_none(c["fit_holdout"][j])} if HELD in c else {})

    def best(self, i: int = 0, *, device: bool = True) -> Model:
        """The candidate of rank `i` as a `Model` (parameters exactly as searched);
        `device=False`: its arrays as NumPy arrays, without the transfer (for code that reads
        them on the host, as `estimate` does with hundreds of candidates)."""
        from .._boundary import check_rank

        i = check_rank("SearchResult.best", i, len(self))
        r = self._row(i)
        c, j = self.columns, int(self.rank[i])
        structure = Structure(r["n"], r["m"])
        f64 = np.float64
        # every array in one transfer (a `device` call per field cost 0.6 s of `estimate` on
        # 100 records, which builds about 800 candidates' models)
        put = jax.device_put if device else (lambda x: x)
        a, b, offset, delays, theta, J, J_rel, cond, status = put((
            np.asarray(r["a"], f64), tuple(np.asarray(bk, f64) for bk in r["b"]),
            np.asarray(r["offset"] or 0.0, f64), np.asarray(r["delays"], f64),
            np.asarray(_compact_theta(c["theta"][j], r["n"], r["m"], self), f64),
            np.asarray(c["J_raw"][j], f64), np.asarray(c["J"][j], f64),
            np.asarray(c["cond"][j], f64), np.asarray(int(c["status"][j]), np.int32)))
        return Model(
            a=a, b=b, offset=offset, delays=delays, theta=theta, J=J, J_rel=J_rel, cond=cond,
            status=status,
            mf=as_values(ModulatingFunction(r["N"], r["M"], r["h"])),  # as identify's
            structure=structure,
            intersample=self.intersample,
            has_offset=self.has_offset,
            output_name=self.output_name,
            input_names=self.input_names,
        )

    def table(self, top: int | None = 10) -> str:
        """Readable table of the best `top` candidates (None: all; a hold-out search,
        `estimate`'s: its held-out E and fit %, which it is ranked by, in place of the
        in-sample ones)."""
        held = HELD in self.columns
        E, fit = ("E_holdout", "fit_holdout") if held else ("E", "fit")
        head = (f"{'rank':>4} {'n':>2} {'m':>8} {'N':>4} {'M':>4} {'h':>9} {'delays':>14} "
                f"{'J':>10} {'E held-out' if held else 'E':>11} "
                f"{'fit% h-o' if held else 'fit%':>8} {'aic':>10} {'bic':>10}  status")
        lines = [head]
        for i in range(len(self) if top is None else min(_top("table", top), len(self))):
            r = self._row(i)
            lines.append(
                f"{r['rank']:>4} {r['n']:>2} {','.join(map(str, r['m'])):>8} {r['N']:>4} "
                f"{r['M']:>4} {r['h']:>9.4g} {','.join(f'{d:g}' for d in r['delays']):>14} "
                f"{_fmt(r['J'], '.3e'):>10} {_fmt(r[E], '.4e'):>11} {_fit_text(r[fit]):>8} "
                f"{_fmt(r['aic'], '.1f'):>10} {_fmt(r['bic'], '.1f'):>10}  {r['status']}"
            )
        return "\n".join(lines)

    def to_dict(self, top: int | None = None, *, _fn: str = "to_dict") -> dict:
        rows = [self._row(i) for i in range(len(self) if top is None
                                            else min(_top(_fn, top), len(self)))]
        # the labels the rows' delays, b and offset refer to (a saved table named no column)
        return {"score": self.score, "candidates": len(self), "compile_s": self.compile_s,
                "run_s": self.run_s, "output_name": self.output_name,
                "input_names": list(self.input_names), "intersample": list(self.intersample),
                "has_offset": bool(self.has_offset),
                # the windows E, fit, AIC and BIC refer to (None: the defaults)
                "identify": None if self.identify is None else [list(w) for w in self.identify],
                "validate": None if self.validate is None else list(self.validate),
                "observer_window": self.observer_window, "ranked": rows}

    def to_json(self, path=None, top: int | None = None) -> str:
        text = json.dumps(self.to_dict(top, _fn="to_json"))
        if path is not None:  # a temporary file renamed over `path`, as every file mfmjax writes
            from .._persist import atomic_write

            atomic_write(path, text.encode())
        return text

    def to_pandas(self):
        """All candidates, ranked, as a pandas DataFrame (pandas is optional)."""
        import pandas as pd

        return pd.DataFrame([self._row(i) for i in range(len(self))])


def _compact_theta(theta_pad, n, m, res: SearchResult):
    parts = [theta_pad[: n + 1]]
    pos = res.n_max + 1
    for k, mk in enumerate(res.m_max):
        parts.append(theta_pad[pos : pos + m[k] + 1])
        pos += mk + 1
    if res.has_offset:
        parts.append(theta_pad[pos : pos + 1])
    return np.concatenate(parts)


def _fmt(v, spec):
    return "-" if v is None else format(v, spec)


def _fit_text(v) -> str:
    """A fit % in the table: below -1000 as "<-1000" (an unstable row's 70-digit fit pushed
    the columns after it out of line), as `Estimate.summary` prints it."""
    return "-" if v is None else "<-1000" if v < -1000 else format(v, ".2f")


HELD = "E_holdout"  # a hold-out search's column (`_selection.holdout_search`)


def ranking(key, n_par, bad, tie: float | None) -> np.ndarray:
    """Candidate order: usable before flagged, then by score, fewer parameters on equal scores;
    every usable candidate within `tie` of the best score is tied with it, and the tied group
    comes first ordered by parameter count (so the rule does not depend on bucket edges)."""
    order = np.lexsort((n_par, key, bad))
    if tie is None or not np.any(~bad & np.isfinite(key)):
        return order
    best = np.min(key[~bad])
    tied = ~bad & (key <= best + tie)
    first = np.flatnonzero(tied)[np.lexsort((key[tied], n_par[tied]))]
    return np.concatenate([first, order[~tied[order]]])


def collect(cols, combos, structs, signals, static, score, t_compile, t_run, where: dict):
    g, st = cols.pop("group"), cols.pop("struct")
    grid = np.asarray([(c[0], c[1], c[2]) for c in combos])
    cols["n"] = np.asarray([s[0] for s in structs])[st]
    cols["m"] = np.asarray([s[1] for s in structs]).reshape(len(structs), -1)[st]
    cols["N"], cols["M"], cols["h"] = grid[g, 0], grid[g, 1], grid[g, 2]
    cols["delays"] = np.asarray([c[3] for c in combos]).reshape(len(combos), -1)[g]
    key = {"E": cols["E"], "J": cols["J"], "fit": -cols["fit"], "aic": cols["aic"],
           "bic": cols["bic"]}[score]
    key = np.where(np.isfinite(key), key, np.inf)
    tie = None  # candidates within `tie` of the best usable score are tied: fewer parameters win
    if score == "E":  # E below rounding noise (1e-12 of the output's variation energy)
        v_start = int(where["v_start"])
        yv = np.asarray(signals.y)[v_start : v_start + int(where["v_valid"])]
        tie = E_TIE_RTOL * float(np.sum((yv - np.mean(yv)) ** 2)) * signals.dt
    if score == "J":  # J below sqrt(p eps) is the float64 noise of theta' G theta
        tie = math.sqrt(cols["theta"].shape[1] * np.finfo(np.float64).eps)
    n_par = np.asarray([s[0] + sum(mk + 1 for mk in s[1]) for s in structs])[st]
    # linearly dependent inputs (u2 = 2 u1): no candidate can split their gain, and the Gram's
    # conditioning test misses it under output noise
    dependent, _ = dependent_candidates(signals, cols["delays"])
    cols["status"] = np.where(dependent, cols["status"] | Status.ILL_CONDITIONED, cols["status"])
    rank = ranking(key, n_par, cols["status"] != 0, tie)
    return SearchResult(
        columns=cols, rank=rank, score=score, n_max=static.n_max, m_max=static.m_max,
        intersample=signals.intersample, has_offset=signals.offset,
        output_name=signals.output_name, input_names=signals.input_names,
        compile_s=t_compile, run_s=t_run,
    )


def _top(fn: str, top) -> int:
    """`top` of `table`/`to_dict`: a whole number >= 1 (-1 and 0 gave an empty table)."""
    from .._boundary import integer

    return integer(f"SearchResult.{fn}", "top", top, lo=1,
                   fix="give how many of the best candidates to show")
