"""Scenarios: the typed model (:mod:`.model`), YAML parsing with errors that name the field and
the fix (:mod:`.parse`), the checks of each method's assumptions (:mod:`.check`), random
valid fleets (:mod:`.generate`), the truth model every simulator runs (:mod:`.truth`) and each
agent's logic as the scenario defines it (:mod:`.agents`). No rclpy."""
from ..core.errors import ScenarioError
from .check import check_scenario
from .model import (Agent, BearingPerturbation, Neighbour, Noise, RandomInit, Scenario,
                    SimulationRates, initial_estimates)
from .parse import load_scenario, parse_scenario, read_scenario_data

__all__ = ['Agent', 'BearingPerturbation', 'Neighbour', 'Noise', 'RandomInit', 'Scenario',
           'ScenarioError', 'SimulationRates', 'check_scenario', 'initial_estimates',
           'load_scenario', 'parse_scenario', 'read_scenario_data']
