"""Loaders for the real DaISy records used in the README's validation table.

The files are not redistributed with mfmjax (DaISy states no license; its terms ask users to
cite it, see each dataset's README). They are read from `path`, else from the folder named by
the environment variable `MFMJAX_DATA`, else from `../shared/data` beside a source checkout.
Citation: De Moor B.L.R. (ed.), DaISy: Database for the Identification of Systems, ESAT/STADIUS,
KU Leuven, http://homes.esat.kuleuven.be/~smc/daisy/.
"""

from __future__ import annotations

import os

import numpy as np

from .._signals import Signals, read_csv

# name: (folder, file, columns, output, inputs, dt, intersample, description)
ROWS = {"heat_exchanger": 4000, "dryer": 867, "glass_furnace": 1247, "heating_system": 801}
DAISY = {
    "heat_exchanger": ("daisy-heat-exchanger", "exchanger.dat", ["t", "q", "theta"], "theta",
                       ["q"], 1.0, "foh", "liquid-saturated steam heat exchanger (97-002): "
                       "flow rate -> outlet temperature, Ts = 1 s"),
    "dryer": ("daisy-industrial-dryer", "dryer2.dat",
              ["k", "fuel", "fan", "feed", "dry_bulb", "wet_bulb", "moisture"], "dry_bulb",
              ["fuel", "fan", "feed"], 10.0, "zoh", "industrial dryer: fuel, fan speed, raw "
              "material flow -> dry-bulb temperature, Ts = 10 s"),
    "glass_furnace": ("daisy-glass-furnace", "glassfurnace.dat",
                      ["k", "heat1", "cool", "heat2", "y1", "y2", "y3", "y4", "y5", "y6"], "y1",
                      ["heat1", "cool", "heat2"], 1.0, "zoh", "glass furnace (Philips): two "
                      "heating inputs, one cooling input -> temperature y1, Ts = 1 sample"),
    "heating_system": ("daisy-heating-system", "heating_system.dat", ["t", "u", "y"], "y", ["u"],
                       2.0, "zoh", "heating system: lamp voltage -> plate temperature, "
                       "Ts = 2 s"),
}


def _locate(folder: str, file: str, path) -> str:
    here = os.path.dirname(os.path.abspath(__file__))
    if path is not None:
        if not os.path.isfile(path):
            raise FileNotFoundError(f"daisy(): no file {path}; give the DaISy file's path, or "
                                    "leave path out to search MFMJAX_DATA and ../shared/data")
        return str(path)
    candidates = []
    if os.environ.get("MFMJAX_DATA"):
        candidates.append(os.path.join(os.environ["MFMJAX_DATA"], folder, file))
        candidates.append(os.path.join(os.environ["MFMJAX_DATA"], file))
    for root in (os.getcwd(), os.path.join(here, "..", "..")):
        candidates.append(os.path.join(root, "..", "shared", "data", folder, file))
    for c in candidates:
        if os.path.isfile(c):
            return c
    raise FileNotFoundError(
        f"daisy(): cannot find {folder}/{file}; download it from DaISy "
        "(http://homes.esat.kuleuven.be/~smc/daisy/) and pass path=..., or set MFMJAX_DATA"
    )


def daisy(name: str, *, path=None, offset: bool = True, output: str | None = None) -> Signals:
    """One DaISy record as `Signals` (`name` in `DAISY`: heat_exchanger, dryer, glass_furnace,
    heating_system). `output` picks another output column (e.g. "wet_bulb", "y3").

    Unlike `Signals`, whose default `offset=None` lets the data decide, the loader's default
    is `offset=True` (the term estimated, whatever the record's level); pass `offset=None` for
    the data's decision, as `benchmarks/real_data.py` does. Times start at t0 = 0 at the first
    row (the files' own time or sample-index column, `t` or `k`, is not read)."""
    if name not in DAISY:
        raise ValueError(f"daisy(): unknown dataset {name!r}; use one of {sorted(DAISY)}")
    folder, file, cols, out, inputs, dt, inter, _ = DAISY[name]
    where = _locate(folder, file, path)
    try:
        data = read_csv(where, names=cols)
    except ValueError as err:  # read_csv's message names --names, a CLI flag
        if "fields but" not in str(err):
            raise
        raise ValueError(f"daisy(): {where} does not have the {len(cols)} columns of {name} "
                         f"({', '.join(cols)}): {str(err).split(': ', 1)[-1].split(' but ')[0]}"
                         f"; check path= (the file {file} of DaISy's {folder})") from None
    rows = len(next(iter(data.values())))
    if path is not None and rows != ROWS[name]:  # a file given: another record of as many
        # columns (the heating system's loaded as the heat exchanger: 801 samples labelled
        # dt = 1, q -> theta; an audit); a record found by its own folder and name is read
        raise ValueError(f"daisy(): {where} has {rows} rows, {name} has {ROWS[name]}; check "
                         f"path= (the file {file} of DaISy's {folder})")
    out = output or out
    outputs = [c for c in cols if c not in inputs and c not in ("t", "k")]
    if out not in outputs:  # the time or sample-index column is no output
        raise ValueError(f"daisy(): {name} has no output column {out!r}; its outputs are "
                         f"{outputs}")
    return Signals(data[out], np.column_stack([data[c] for c in inputs]), dt=dt,
                   intersample=inter, offset=offset, output_name=out, input_names=inputs)
