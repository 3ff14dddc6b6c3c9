#!/usr/bin/env bash
# One task per object on a real scheduler: a one-node Slurm (munged, slurmctld and slurmd as
# root, Debian's slurm-wlm and munge) and a cache server (nginx with WebDAV) started here on
# 127.0.0.1. examples/slurm/convert-library plans a library and submits a job array (one task
# per object) and the assembly (afterok); one task is requeued while it trains, as when its
# node fails; the assembled manifest and assets equal a single `lsnif batch` run byte for byte.
# Exit 77 (CTest: skipped) when the daemons cannot be started here.
# usage: slurm_array.sh LSNIF_BINARY PROJECT_DIR MESH_DIR EXAMPLE_SCENE_GLB WORK_DIR
set -uo pipefail
lsnif=$1 project=$2 meshes=$3 scene=$4 work=$5
fail=0
bad() { echo "FAIL: $*"; fail=1; }
. "$(dirname "$0")/../skip.sh"
skip() { skip_or_fail slurm "$@"; }
rm -rf "$work" && mkdir -p "$work"/{lib/sub,run,state,spool,log,srv,nginx}
for tool in munged slurmctld slurmd sbatch scontrol squeue nginx curl; do
  command -v "$tool" >/dev/null || [[ -x /usr/sbin/$tool ]] || skip "$tool is not installed (scripts/setup installs slurm-wlm, munge, nginx, curl)"
done
[[ $(id -u) == 0 ]] || skip "the one-node Slurm runs its daemons as root"
[[ -r /etc/munge/munge.key ]] || skip "no /etc/munge/munge.key (Debian's munge package creates it)"
cp "$meshes/ChineseDragon-10kv.off" "$work/lib/"
cp "$meshes/armadillo.off" "$work/lib/sub/"
cp "$scene" "$work/lib/scene.glb"

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
pids=()
cleanup() {
  for f in "$work"/run/*.pid; do [[ -f $f ]] && kill "$(cat "$f")" 2>/dev/null; done
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null; done
}
trap cleanup EXIT

# munged on a socket of its own, as its own user.
chown munge:munge "$work/run" && chmod 755 "$work"
runuser -u munge -- "$(command -v munged || echo /usr/sbin/munged)" --socket="$work/run/munge.socket" \
  --pid-file="$work/run/munged.pid" --log-file="$work/run/munged.log" --seed-file="$work/run/munge.seed" \
  || skip "munged did not start: $(tail -2 "$work/run/munged.log" 2>/dev/null)"

host=$(hostname -s)
ctld_port=$(free_port) slurmd_port=$(free_port)
export SLURM_CONF=$work/slurm.conf
cat >"$SLURM_CONF" <<EOF
ClusterName=lsnif-test
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$work/run/munge.socket
CredType=cred/munge
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/run/slurmctld.pid
SlurmdPidFile=$work/run/slurmd.pid
SlurmctldLogFile=$work/log/slurmctld.log
SlurmdLogFile=$work/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
JobRequeue=1
NodeName=$host NodeAddr=127.0.0.1 CPUs=$(nproc) State=UNKNOWN
PartitionName=lsnif Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
chown -R munge:munge "$work/run"
slurmctld -f "$SLURM_CONF" || skip "slurmctld did not start: $(tail -3 "$work/log/slurmctld.log" 2>/dev/null)"
slurmd -f "$SLURM_CONF" || skip "slurmd did not start: $(tail -3 "$work/log/slurmd.log" 2>/dev/null)"
for _ in $(seq 100); do
  grep -q idle <<<"$(sinfo -h -o %T 2>/dev/null)" && break
  sleep 0.2
done
grep -q idle <<<"$(sinfo -h -o %T 2>/dev/null)" || skip "the Slurm node did not come up: $(tail -3 "$work/log/slurmd.log" 2>/dev/null)"

# The cache server.
port=$(free_port)
cat >"$work/nginx.conf" <<EOF
daemon off;
master_process off;
pid $work/run/nginx.pid;
error_log $work/log/nginx.log;
events { worker_connections 64; }
http {
    access_log off;
    client_body_temp_path $work/nginx/body;
    server {
        listen 127.0.0.1:$port;
        root $work/srv;
        location / { dav_methods PUT; create_full_put_path on; client_max_body_size 0; }
    }
}
EOF
nginx -c "$work/nginx.conf" -p "$work" & pids+=($!)
for _ in $(seq 50); do curl -s -o /dev/null "http://127.0.0.1:$port/" && break; sleep 0.1; done
curl -s -o /dev/null "http://127.0.0.1:$port/" || skip "nginx did not start: $(tail -2 "$work/log/nginx.log")"
cache=http://127.0.0.1:$port/cache

# Plan and submit (the smoke preset: about a second of training per object, caught by polling).
settings=(--preset smoke)
out=$work/out
LSNIF=$lsnif LSNIF_THREADS=1 "$project/examples/slurm/convert-library" "$work/lib" "$out" "$cache" "${settings[@]}" \
  >"$work/submit.txt" 2>"$work/submit.err" || bad "convert-library: exit $? $(cat "$work/submit.err")"
read -r _ array _ _ _ assembly < <(tr -d '(),' <"$work/submit.txt")
tasks=$(python3 -c 'import json,sys; print(len(json.load(open(sys.argv[1]))["tasks"]))' "$out/plan.json")
[[ $tasks -ge 3 ]] || bad "the plan has $tasks tasks"
echo "array $array ($tasks tasks), assembly $assembly"

# Requeue task 0 while it trains (a node failure): Slurm kills and runs it again.
requeued=
for _ in $(seq 600); do
  if grep -q ' train ' "$out/logs/task-0.txt" 2>/dev/null; then
    scontrol requeue "${array}_0" && requeued=1
    break
  fi
  sleep 0.1
done
[[ -n $requeued ]] || bad "task 0 was never seen training: $(cat "$out/logs/task-0.txt" 2>/dev/null | tail -3)"
state() { scontrol show job "$1" 2>/dev/null | grep -o 'JobState=[A-Z_]*' | head -1 | cut -d= -f2; }
# A requeued job waits (BeginTime) before it may start again: once it is pending, let it start now.
for _ in $(seq 100); do
  [[ $(state "${array}_0") == PENDING ]] && scontrol update JobId="${array}_0" StartTime=now >/dev/null 2>&1 && break
  sleep 0.1
done
for _ in $(seq 1800); do
  s=$(state "$assembly")
  [[ $s == COMPLETED || $s == FAILED || $s == CANCELLED || $s == TIMEOUT ]] && break
  sleep 0.2
done
[[ $(state "$assembly") == COMPLETED ]] || bad "the assembly is $(state "$assembly"): $(tail -5 "$out/logs/assembly.txt" 2>/dev/null)"
restarts=$(scontrol show job "${array}_0" 2>/dev/null | grep -o 'Restarts=[0-9]*' | cut -d= -f2)
[[ ${restarts:-0} -ge 1 ]] || bad "task 0 was not run again (Restarts=${restarts:-?})"
[[ $(grep -c ' import ' "$out/logs/task-0.txt") -ge 2 ]] || bad "task 0's log shows no second run"
[[ $(find "$work/srv/cache" -name '*.entry' | wc -l) == "$tasks" ]] || bad "the cache server holds not one entry per task"

# The same as one lsnif batch run on the same library and settings.
"$lsnif" batch "$work/lib" -o "$work/single" --cache "$work/single_cache" "${settings[@]}" >/dev/null 2>&1 \
  || bad "single run: exit $?"
cmp -s "$work/single/manifest.json" "$out/manifest.json" || bad "the assembled manifest differs from a single run's"
shipped=$(find "$work/single" -name '*.lsnif' | wc -l)
[[ $shipped -ge 2 ]] || bad "the single run shipped $shipped assets: the comparison needs some"
for a in "$work/single"/*.lsnif; do cmp -s "$a" "$out/$(basename "$a")" || bad "$(basename "$a") differs"; done
python3 -c "import sys, xml.etree.ElementTree as ET; r = ET.parse(sys.argv[1]).getroot(); assert r.find('testsuite').get('failures') == '0'" \
  "$out/junit.xml" || bad "junit.xml"

[[ $fail == 0 ]] && echo "PASS: Slurm job array, one task requeued, == a single run"
exit $fail
