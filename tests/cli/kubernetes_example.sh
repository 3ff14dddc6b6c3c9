#!/usr/bin/env bash
# examples/kubernetes as far as this machine can take it (Debian 12 has no Kubernetes to run it
# on): `submit --print` plans a library and renders the two Jobs; they are checked as an
# Indexed Job with one completion per task, and each pod's command is run here with its
# environment from the YAML and JOB_COMPLETION_INDEX set, then the assembly's; the result
# equals a single `lsnif batch` run byte for byte.
# usage: kubernetes_example.sh LSNIF_BINARY PROJECT_DIR MESH_DIR WORK_DIR
set -uo pipefail
lsnif=$(realpath "$1") project=$2 meshes=$3 work=$4
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work/library/lib/sub" "$work/bin"
cp "$meshes/ChineseDragon-10kv.off" "$work/library/lib/"
cp "$meshes/armadillo.off" "$work/library/lib/sub/"
ln -s "$lsnif" "$work/bin/lsnif"  # the pods run `lsnif` from the image's PATH
export PATH=$work/bin:$PATH

LSNIF=$lsnif IMAGE=registry.example.org/lsnif:1 CLAIM=assets THREADS=1 \
  "$project/examples/kubernetes/submit" --print "$work/library" out "$work/cache" --preset smoke \
  >"$work/jobs.yaml" 2>"$work/submit.err" || bad "submit --print: exit $? $(cat "$work/submit.err")"

# The Jobs as Kubernetes reads them, then every pod's command run here.
python3 - "$work/jobs.yaml" "$work/library/out/plan.json" "$work/library" <<'PY' || bad "the rendered Jobs"
import json, os, subprocess, sys, yaml
jobs, plan, library = list(yaml.safe_load_all(open(sys.argv[1]))), json.load(open(sys.argv[2])), sys.argv[3]
tasks = len(plan["tasks"])
assert tasks == 2, tasks
indexed, assembly = jobs
assert indexed["kind"] == assembly["kind"] == "Job" and indexed["apiVersion"] == "batch/v1"
spec = indexed["spec"]
assert spec["completionMode"] == "Indexed" and spec["completions"] == tasks, spec
assert spec["backoffLimitPerIndex"] >= 1 and spec["template"]["spec"]["restartPolicy"] == "Never"
for job in jobs:
    pod = job["spec"]["template"]["spec"]
    c = pod["containers"][0]
    assert c["image"] == "registry.example.org/lsnif:1"
    assert pod["volumes"][0]["persistentVolumeClaim"]["claimName"] == "assets"
    assert c["volumeMounts"][0]["mountPath"] == library  # where the plan's paths point
def run(job, index=None):
    c = job["spec"]["template"]["spec"]["containers"][0]
    env = dict(os.environ)
    env.update({e["name"]: str(e["value"]) for e in c["env"] if "value" in e})
    if index is not None:
        env["JOB_COMPLETION_INDEX"] = str(index)
    r = subprocess.run(c["command"], env=env, capture_output=True, text=True)
    assert r.returncode == 0, (c["command"], r.returncode, r.stderr[-800:])
    return r.stdout
for k in range(tasks):
    out = run(indexed, k)
    assert out.startswith("lsnif    "), out
print(run(assembly), end="")
PY
"$lsnif" batch "$work/library/lib" -o "$work/library/single" --cache "$work/single_cache" --preset smoke >/dev/null 2>&1 \
  || bad "single run: exit $?"
cmp -s "$work/library/single/manifest.json" "$work/library/out/manifest.json" || bad "the assembled manifest differs from a single run's"
for a in "$work/library/single"/*.lsnif; do cmp -s "$a" "$work/library/out/$(basename "$a")" || bad "$(basename "$a") differs"; done
[[ -f $work/library/out/junit.xml ]] || bad "the assembly wrote no junit.xml"

[[ $fail == 0 ]] && echo "PASS: the Kubernetes example's Jobs run here == a single run"
exit $fail
