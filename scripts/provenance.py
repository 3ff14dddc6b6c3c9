"""Where a measurement comes from: the date, the commit, the machine and the lsnif that made it.

Every measuring script (bench_table, eval_scenes, tradeoff, sizing_chart, seed_sweep,
failure_modes) stores `provenance(LSNIF)` in its JSON, and every chart and generated table
prints `caption(...)` of it, so a figure says which code and which CPU it describes.
"""
import os
import subprocess
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# What the measured binaries are built from.
CODE = ["CMakeLists.txt", "CMakePresets.json", "base", "converter", "examples", "format", "trainer"]


def _output(cmd):
    try:
        return subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def cpu_model():
    """lscpu's model name, with the family and model where the name alone does not say which
    generation it is, and the CPUs this process may use ("AMD EPYC (family 26, model 2), 2 vCPU")."""
    info = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                info.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    model = info.get("model name", "unknown CPU")
    if not any(c.isdigit() for c in model) and "cpu family" in info:
        model += f" (family {info['cpu family']}, model {info.get('model', '?')})"
    return f"{model}, {len(os.sched_getaffinity(0))} vCPU"


def provenance(lsnif):
    """The record stored in a measurement's JSON under "provenance"."""
    commit = _output(["git", "-C", ROOT, "rev-parse", "--short=12", "HEAD"])
    # Changes to the documents being written while measuring do not make the code another one.
    dirty = bool(_output(["git", "-C", ROOT, "status", "--porcelain", "--untracked-files=no", "--", *CODE]))
    version = _output([lsnif, "--version"]).splitlines()
    return {
        "date": time.strftime("%Y-%m-%d", time.gmtime()),
        "commit": commit + ("+changes" if dirty else ""),
        "machine": cpu_model(),
        "lsnif": version[0] if version else "",
        "identity": version[1].split()[-1] if len(version) > 1 else "",
    }


def caption(p):
    """One line for a chart or table: "2026-11-27, commit 5ea4bcb6a1f2, AMD EPYC ..., 2 vCPU"."""
    return f"{p['date']}, commit {p['commit']}, {p['machine']}"
