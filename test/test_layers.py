"""The package's import contracts (setup.cfg, ``[importlinter]``): its layers import in one
direction only (core < estimators < runtime < scenario | metrics < sim < studies < plan |
msg_defs < ros < cli), and nothing but ros and msg_defs imports rclpy or the ROS message
packages. Run with import-linter's ``lint-imports``, as a developer would from the repository
root; a broken contract fails with its report."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = 'bearing_pose_estimation'
LINT_IMPORTS = Path(sys.executable).parent / 'lint-imports'


def _lint_imports(package_parent: Path) -> subprocess.CompletedProcess[str]:
    """``lint-imports`` on setup.cfg's contracts, analysing the package found in
    ``package_parent`` (it looks in its working directory first; no cache left behind; wide
    lines, so that the report reads)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(package_parent), *filter(None, [os.environ.get('PYTHONPATH')])]), COLUMNS='200')
    return subprocess.run([str(LINT_IMPORTS), '--no-cache', '--no-logo', str(ROOT / 'setup.cfg')],
                          cwd=package_parent, env=env, capture_output=True, text=True,
                          timeout=300)


def test_the_import_contracts_are_kept():
    proc = _lint_imports(ROOT)
    report = proc.stdout + proc.stderr
    assert proc.returncode == 0, report
    assert 'Contracts: 2 kept, 0 broken.' in report, report


def test_a_broken_contract_fails_with_its_report(tmp_path):
    """The check can fail: a copy of the package whose core imports the simulator (a layer
    above it) and rclpy breaks both contracts, and the report names the import."""
    shutil.copytree(ROOT / PKG, tmp_path / PKG, symlinks=False,
                    ignore=shutil.ignore_patterns('__pycache__'))
    (tmp_path / PKG / 'core' / 'upside_down.py').write_text(
        'from ..sim import batch\nimport rclpy\n')
    proc = _lint_imports(tmp_path)
    report = proc.stdout + proc.stderr
    assert proc.returncode == 1, report
    assert 'Contracts: 0 kept, 2 broken.' in report, report
    assert f'{PKG}.core.upside_down -> {PKG}.sim.batch' in report, report
    assert f'{PKG}.core.upside_down -> rclpy' in report, report
