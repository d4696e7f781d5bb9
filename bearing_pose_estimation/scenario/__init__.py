"""Scenarios: the typed model, YAML parsing, the methods' checks, random valid fleets, the truth
every simulator runs and each agent's runtime as the scenario defines it. No rclpy."""
from ..core.errors import ScenarioError
from .check import check_scenario
from .model import (Agent, BearingPerturbation, Neighbour, Noise, RandomInit, Scenario,
                    SimulationRates, initial_estimates)
from .parse import load_scenario, parse_scenario, read_scenario_data

__all__ = ['Agent', 'BearingPerturbation', 'Neighbour', 'Noise', 'RandomInit', 'Scenario',
           'ScenarioError', 'SimulationRates', 'check_scenario', 'initial_estimates',
           'load_scenario', 'parse_scenario', 'read_scenario_data']
