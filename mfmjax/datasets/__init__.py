"""Built-in datasets: simulated systems with known parameters (real records come later)."""

from ._simulated import paper_table3_model1 as paper_table3_model1
from ._simulated import simulated_experiment as simulated_experiment
from ._simulated import switching_experiment as switching_experiment
from ._simulated import switching_plant as switching_plant
from ._simulated import third_order_two_input as third_order_two_input
