"""Datasets: simulated systems with known parameters, the simulated glass forehearth, and
loaders for real DaISy records."""

from ._daisy import DAISY as DAISY
from ._daisy import daisy as daisy
from ._forehearth import forehearth as forehearth
from ._forehearth import transport_delay as transport_delay
from ._simulated import paper_table3_model1 as paper_table3_model1
from ._simulated import simulated_experiment as simulated_experiment
from ._simulated import switching_experiment as switching_experiment
from ._simulated import switching_plant as switching_plant
from ._simulated import third_order_two_input as third_order_two_input
