"""The closing line's CPU time is the run's own: what this process and its children spent before
the run (imports, an earlier run in the same process) is not counted, what a child spent during
it is, and the share of the cores never passes 100%."""

import re
import subprocess
import sys
import time

from harness.run.execute import CpuUsage

BURN = "import time\nend = time.process_time() + {s}\nwhile time.process_time() < end: pass"


def _burn_in_child(seconds: float) -> None:
    subprocess.run([sys.executable, "-c", BURN.format(s=seconds)], check=True)


def test_cpu_time_is_the_runs_and_its_share_at_most_the_cores():
    _burn_in_child(0.6)  # an earlier run's worker, finished and waited for before this run
    exec(BURN.format(s=0.3))  # this process's own work before the run (and its imports: seconds)
    usage = CpuUsage.now()
    time.sleep(0.2)
    _burn_in_child(0.3)  # a worker of this run
    wall, cpu = usage.since()
    assert 0.3 <= cpu < 0.3 + 0.4, cpu  # the child's 0.3 s and its interpreter's start, no more
    share = int(re.search(r"\((\d+)% of \d+ cores\)", usage.text()).group(1))
    assert share <= 100 * cpu / wall + 1 and share <= 100
