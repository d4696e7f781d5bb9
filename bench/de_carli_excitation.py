"""What De Carli et al.'s excitation monitor costs and what it protects: settling with every
pair in the yaw consensus from t = 0 (``pe_threshold: 0``) against the default monitor, and a
hovering robot's pairs under odometry noise.

    OMP_NUM_THREADS=1 .venv/bin/python bench/de_carli_excitation.py

Batch simulator, records every 10 ms. Settling as every run reports it (studies.summary):
from when the mean errors stay below 1e-3 rad and 1e-2 m, and below the larger of those and 3x
the run's steady floor ("settled"). The transient: the mean position error at 1 s and 2 s and
its integral over the first 5 s. Scenarios:

- paper: config/de_carli_8_quadrotors.yaml as it is (the paper's closed loop), 20 s;
- generated: ``bearing-pose generate --agents 8 --seed 0 --speed 0.3`` made a De Carli fleet
  (yaw-only: each attitude's heading and the z part of its angular velocity; 200 Hz, the
  paper's gains, no leaders): every robot drifts at 0.3 m/s from the start, 20 s;
- noisy: config/de_carli_noisy.yaml (2 cm relative positions, 0.02 m/s odometry, 0.005 rad/s
  gyro noise), 20 s;
- hover: the noisy file, exogenous motion, robot_7 without a formation position (it never
  moves: its odometry is its noise), 100 s; the mean errors over the last 30 s.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

os.environ.setdefault('OMP_NUM_THREADS', '1')

from bearing_pose_estimation.core.motion import yaw_of  # noqa: E402
from bearing_pose_estimation.scenario import parse_scenario  # noqa: E402
from bearing_pose_estimation.scenario.generate import generate_scenario  # noqa: E402
from bearing_pose_estimation.scenario.parse import read_scenario_data  # noqa: E402
from bearing_pose_estimation.sim.batch import BatchSimulator  # noqa: E402
from bearing_pose_estimation.studies.summary import quantities  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / 'config'
RECORD_S = 0.01
MONITORS = (('every pair from t = 0', {'pe_threshold': 0.0}), ('default', {}))


def generated() -> dict[str, Any]:
    """The generated fleet as a De Carli scenario (module docstring)."""
    data = generate_scenario(8, seed=0, speed=0.3)
    parsed = parse_scenario(data)
    data.update(method='de_carli', frequency=200.0, gains={}, sensors={
        'odometry': {'rate': 200.0}, 'relative_positions': {'rate': 200.0}})
    del data['leaders']
    for spec, agent in zip(data['agents'], parsed.agents):
        spec['attitude'] = {'axis': [0, 0, 1], 'angle': float(yaw_of(agent.attitude))}
        spec['angular_velocity'] = [0.0, 0.0, spec['angular_velocity'][2]]
    return data


def hovering() -> dict[str, Any]:
    data = read_scenario_data(CONFIG / 'de_carli_noisy.yaml')
    data['formation_control']['mode'] = 'exogenous'
    for agent in data['agents']:
        if agent['name'] == 'robot_7':
            del agent['formation_position']
    return data


def run(data: dict[str, Any], gains: dict[str, float], duration: float):
    data = {**data, 'gains': {**data.get('gains', {}), **gains}}
    return BatchSimulator(parse_scenario(data)).run(duration, record_every=RECORD_S)


def fmt(value: float | None) -> str:
    return 'never' if value is None else f'{value:.2f}'


def settling() -> None:
    print('| scenario | monitor | attitude < 1e-3 rad from [s] | position < 1e-2 m from [s] '
          '| attitude settled [s] | position settled [s] | position error at 1 s, 2 s [m] '
          '| its integral over 0-5 s [m s] |')
    print('|---|---|---|---|---|---|---|---|')
    for name, data in (('paper', read_scenario_data(CONFIG / 'de_carli_8_quadrotors.yaml')),
                       ('generated', generated()),
                       ('noisy', read_scenario_data(CONFIG / 'de_carli_noisy.yaml'))):
        for label, gains in MONITORS:
            rec = run(data, gains, 20.0)
            q = quantities(rec)
            pos = rec.mean_errors()[1]
            at = {t: int(round(t / RECORD_S)) for t in (1.0, 2.0, 5.0)}
            print(f'| {name} | {label} | {fmt(q["attitude_below_1e-3_rad_from_s"])} '
                  f'| {fmt(q["position_below_1e-2_m_from_s"])} '
                  f'| {fmt(q["attitude_settled_from_s"])} | {fmt(q["position_settled_from_s"])} '
                  f'| {pos[at[1.0]]:.3g}, {pos[at[2.0]]:.3g} '
                  f'| {pos[:at[5.0]].sum() * RECORD_S:.3g} |', flush=True)


def hover() -> None:
    print('\n| hover (100 s) | monitor | mean attitude error, 70-100 s [rad] '
          '| mean position error, 70-100 s [m] | the same, 30-60 s [rad], [m] |')
    print('|---|---|---|---|---|')
    data = hovering()
    for label, gains in MONITORS:
        rec = run(data, gains, 100.0)
        att, pos = rec.mean_errors()
        late, mid = rec.t >= 70.0 - 1e-9, (rec.t >= 30.0 - 1e-9) & (rec.t < 60.0)
        print(f'| hover | {label} | {att[late].mean():.3g} | {pos[late].mean():.3g} '
              f'| {att[mid].mean():.3g}, {pos[mid].mean():.3g} |', flush=True)


if __name__ == '__main__':
    settling()
    hover()
