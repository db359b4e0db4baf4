"""mfmjax: continuous-time system identification with modulating functions, in JAX.

Importing mfmjax enables JAX's float64 mode (`jax_enable_x64`): the Gram matrices of the method
are useless in float32. Every array mfmjax returns is float64.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import datasets as datasets  # noqa: E402
from . import online as online  # noqa: E402
from ._analysis import Comparison as Comparison  # noqa: E402
from ._analysis import FrequencyResponse as FrequencyResponse  # noqa: E402
from ._analysis import Residuals as Residuals  # noqa: E402
from ._analysis import StepResponse as StepResponse  # noqa: E402
from ._analysis import compare as compare  # noqa: E402
from ._analysis import frequency_response as frequency_response  # noqa: E402
from ._analysis import residuals as residuals  # noqa: E402
from ._analysis import step_response as step_response  # noqa: E402
from ._cache import enable_compile_cache as enable_compile_cache  # noqa: E402
from ._cramer_rao import cramer_rao as cramer_rao  # noqa: E402
from ._estimate import Estimate as Estimate  # noqa: E402
from ._estimate import estimate as estimate  # noqa: E402
from ._estimate import estimate_outputs as estimate_outputs  # noqa: E402
from ._gram import gram as gram  # noqa: E402
from ._gram import modulated_signals as modulated_signals  # noqa: E402
from ._identify import identify as identify  # noqa: E402
from ._model import Model as Model  # noqa: E402
from ._modulating import ModulatingFunction as ModulatingFunction  # noqa: E402
from ._modulating import phi as phi  # noqa: E402
from ._modulating import phi_integral as phi_integral  # noqa: E402
from ._modulating import phi_scaled as phi_scaled  # noqa: E402
from ._observers import Observation as Observation  # noqa: E402
from ._observers import final_state as final_state  # noqa: E402
from ._observers import fit_percent as fit_percent  # noqa: E402
from ._observers import initial_state as initial_state  # noqa: E402
from ._observers import moving_final_states as moving_final_states  # noqa: E402
from ._observers import observe as observe  # noqa: E402
from ._observers import performance_index as performance_index  # noqa: E402
from ._online import OnlineConfig as OnlineConfig  # noqa: E402
from ._online import OnlineIdentifier as OnlineIdentifier  # noqa: E402
from ._online import OnlineOutputs as OnlineOutputs  # noqa: E402
from ._online import OnlineState as OnlineState  # noqa: E402
from ._output_error import OutputErrorFit as OutputErrorFit  # noqa: E402
from ._output_error import output_error as output_error  # noqa: E402
from ._persist import load_covariance as load_covariance  # noqa: E402
from ._persist import load_model as load_model  # noqa: E402
from ._persist import save_model as save_model  # noqa: E402
from ._prepare import Trend as Trend  # noqa: E402
from ._prepare import detrend as detrend  # noqa: E402
from ._prepare import resample as resample  # noqa: E402
from ._quadrature import kernel_weights as kernel_weights  # noqa: E402
from ._refine import Refinement as Refinement  # noqa: E402
from ._refine import refine as refine  # noqa: E402
from ._refine import scores as scores  # noqa: E402
from ._search import SearchResult as SearchResult  # noqa: E402
from ._search import search as search  # noqa: E402
from ._signals import Signals as Signals  # noqa: E402
from ._simulate import simulate as simulate  # noqa: E402
from ._solve import closed_form as closed_form  # noqa: E402
from ._solve import public_constrained_solve as constrained_solve  # noqa: E402
from ._srivc import SrivcFit as SrivcFit  # noqa: E402
from ._srivc import srivc as srivc  # noqa: E402
from ._statespace import StateSpace as StateSpace  # noqa: E402
from ._statespace import state_space as state_space  # noqa: E402
from ._statespace import to_control as to_control  # noqa: E402
from ._statespace import to_scipy as to_scipy  # noqa: E402
from ._status import Status as Status  # noqa: E402
from ._structure import Structure as Structure  # noqa: E402

__version__ = "0.1.0"

__all__ = [  # the public names (tests/test_fuzz.py covers each one)
    "Model", "ModulatingFunction", "Observation", "OnlineConfig", "OnlineIdentifier",
    "OnlineOutputs", "OnlineState", "OutputErrorFit", "Refinement", "SearchResult", "Signals",
    "StateSpace", "Status", "Structure", "closed_form", "constrained_solve", "cramer_rao",
    "datasets", "enable_compile_cache", "Estimate", "estimate", "estimate_outputs",
    "final_state", "fit_percent", "gram", "identify",
    "initial_state", "kernel_weights", "load_covariance", "load_model", "modulated_signals", "moving_final_states",
    "observe", "online", "output_error", "performance_index", "phi", "phi_integral", "phi_scaled",
    "refine", "save_model", "scores", "search", "simulate", "srivc", "SrivcFit", "state_space",
    "to_control",
    "to_scipy", "Comparison", "FrequencyResponse", "Residuals", "StepResponse", "compare",
    "frequency_response", "residuals", "step_response", "Trend", "detrend", "resample",
]
