"""Shared set-up of the ROS tests: real DDS, kept on this machine and off other runs' domains."""

import os

# Before any rclpy context exists: discovery on localhost only, and a domain of our own so
# that parallel CI jobs and a user's running ROS graph never see each other.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(11 + os.getpid() % 90))
os.environ.pop('ROS_LOCALHOST_ONLY', None)
os.environ.setdefault('RERUN_ANALYTICS', '0')


# Tests write to tmp_path, never into the repository: the checkout's status (untracked and
# changed files) must be the same after the run as before it.
_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _repo_status() -> set[str] | None:
    import subprocess
    try:
        out = subprocess.run(['git', 'status', '--porcelain', '--untracked-files=all'],
                             cwd=_REPO, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return set(out.stdout.splitlines()) if out.returncode == 0 else None


def pytest_sessionstart(session):
    session.config._repo_status_before = _repo_status()


def pytest_sessionfinish(session, exitstatus):
    before = getattr(session.config, '_repo_status_before', None)
    after = _repo_status()
    if before is None or after is None:
        return
    left = sorted(after - before)
    if left:
        print('\ntests left files in the repository:\n  ' + '\n  '.join(left))
        session.exitstatus = 1
