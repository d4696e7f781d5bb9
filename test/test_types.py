"""The package type-checks: mypy (pinned in requirements.txt, configured in setup.cfg) reports
nothing on bearing_pose_estimation and msg_defs."""
import subprocess
import sys


def test_the_package_type_checks(repo_root):
    proc = subprocess.run([sys.executable, '-m', 'mypy'], cwd=repo_root, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert 'Success: no issues found' in proc.stdout
