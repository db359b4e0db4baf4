"""The on-line identifier's explicit-state API (Algorithm 1): `init`, `update`, `save`, `load`.

    state = mfmjax.online.init(mfmjax.OnlineConfig(dt=1.0, n_inputs=2))
    state, out = mfmjax.online.update(state, t, y, u)   # any chunk size
"""

from ._online import OnlineConfig as OnlineConfig
from ._online import OnlineIdentifier as OnlineIdentifier
from ._online import OnlineOutputs as OnlineOutputs
from ._online import OnlineState as OnlineState
from ._online import init as init
from ._online import load as load
from ._online import model_table as model_table
from ._online import save as save
from ._online import update as update
