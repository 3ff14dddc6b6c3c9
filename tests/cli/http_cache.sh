#!/usr/bin/env bash
# lsnif's cache on an HTTP server: nginx with WebDAV PUT, started here on 127.0.0.1 (as
# examples/cache-server sets it up). Cold and warm runs through the server (the same bytes as a
# directory cache), a flipped byte, a foreign entry and a truncated entry on the server (each
# reported, converted again, stored anew), a writer killed half-way, read-only mode, a local
# level in front, a server down, answering 500 or silent (warnings, never a failed build),
# a token (writes refused without it, never printed or recorded), URLs refused, two writers
# at once, the server stopped mid-run, and the example server's rules.
# Conversions train 40 steps: the cache, not the training, is under test.
# Exit 77 (CTest: skipped) when nginx cannot be started here.
# usage: http_cache.sh LSNIF_BINARY PROJECT_DIR MESH_DIR WORK_DIR
set -uo pipefail
lsnif=$1 project=$2 meshes=$3 work=$4
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work/lib" "$work/srv" "$work/logs"
cp "$meshes/ChineseDragon-10kv.off" "$meshes/armadillo.off" "$work/lib/"

nginx=$(command -v nginx || echo /usr/sbin/nginx)
. "$(dirname "$0")/../skip.sh"
[[ -x $nginx ]] || skip_or_fail nginx "nginx is not installed (scripts/setup installs it)"
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
dead_port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
cat >"$work/nginx.conf" <<EOF
daemon off;
master_process off;
worker_processes 1;
pid $work/nginx.pid;
error_log $work/logs/error.log;
events { worker_connections 64; }
http {
    access_log $work/logs/access.log;
    client_body_temp_path $work/logs/body;
    proxy_temp_path $work/logs/proxy;
    fastcgi_temp_path $work/logs/fastcgi;
    uwsgi_temp_path $work/logs/uwsgi;
    scgi_temp_path $work/logs/scgi;
    map "\$request_method:\$http_authorization" \$refused {
        default 1;
        "~^(GET|HEAD):" 0;
        "PUT:Bearer s3cret-t0ken" 0;
    }
    server {
        listen 127.0.0.1:$port;
        root $work/srv;
        location / {
            dav_methods PUT;
            create_full_put_path on;
            client_max_body_size 0;
        }
        location /protected/ {
            if (\$refused) { return 403; }
            dav_methods PUT;
            create_full_put_path on;
            client_max_body_size 0;
        }
        location /broken/ { return 500; }
    }
}
EOF
start_nginx() {
  "$nginx" -c "$work/nginx.conf" -p "$work" 2>>"$work/logs/start.err" &
  nginx_pid=$!
  for _ in $(seq 50); do
    curl -s -o /dev/null "http://127.0.0.1:$port/" && return 0
    sleep 0.1
  done
  return 1
}
stop_nginx() { kill "$nginx_pid" 2>/dev/null; wait "$nginx_pid" 2>/dev/null; }
trap 'stop_nginx; [[ -n ${silent_pid:-} ]] && kill $silent_pid 2>/dev/null' EXIT
start_nginx || skip_or_fail nginx "nginx did not start on 127.0.0.1:$port: $(cat "$work/logs/start.err" "$work/logs/error.log" 2>/dev/null | tail -3)"

url=http://127.0.0.1:$port
run() {  # run NAME ARGS...: lsnif batch on the library into $work/NAME with the given cache options
  local name=$1; shift
  "$lsnif" batch "$work/lib" -o "$work/$name" --preset smoke --steps 40 --threads 2 --json "$@" \
    >"$work/$name.json" 2>"$work/$name.err"; rc=$?
}
summary() {  # summary NAME EXPR: a Python expression on the --json summary `s` must hold
  python3 -c "import json,sys; s=json.load(open(sys.argv[1])); assert $2, s" "$work/$1.json" >/dev/null 2>&1 \
    || bad "$1: $2 does not hold: $(head -c 400 "$work/$1.json") $(head -c 400 "$work/$1.err")"
}
entries() { find "$work/srv/$1" -name '*.entry' 2>/dev/null | sort; }

# A directory cache: the reference every server run must equal.
run reference --cache "$work/dircache"; [[ $rc == 0 ]] || bad "reference: exit $rc"
same_as_reference() {  # the manifest and every asset byte for byte
  cmp -s "$work/reference/manifest.json" "$work/$1/manifest.json" || bad "$1: manifest differs from a directory cache's"
  for a in "$work/reference"/*.lsnif; do cmp -s "$a" "$work/$1/$(basename "$a")" || bad "$1: $(basename "$a") differs"; done
}

# Cold and warm through the server.
run cold --cache "$url/lib-cache"; [[ $rc == 0 ]] || bad "cold: exit $rc"
summary cold 's["cache"]["stored"] == 2 and s["cache"]["hits"] == 0 and s["cache"]["location"].startswith("http://")'
[[ $(entries lib-cache | wc -l) == 2 ]] || bad "cold: the server holds $(entries lib-cache | wc -l) entries, not 2"
same_as_reference cold
run warm --cache "$url/lib-cache/"; [[ $rc == 0 ]] || bad "warm: exit $rc"
summary warm 's["cache"]["hits"] == 2 and s["cache"]["stored"] == 0'
same_as_reference warm
grep -q '^warning:' "$work/warm.err" && bad "warm: unexpected warnings: $(grep '^warning:' "$work/warm.err")"
# The server stores exactly the directory cache's bytes, in the same layout.
for e in $(entries lib-cache); do
  cmp -s "$e" "$work/dircache/v1/entries/${e#"$work/srv/lib-cache/v1/entries/"}" || bad "server entry $e differs from the directory cache's"
done

# Damaged on the server: a flipped byte, a foreign entry (another key's), a truncated one.
mapfile -t served < <(entries lib-cache)
damage() {  # damage NAME HOW: damage the first entry, run, expect one corrupt entry replaced
  local name=$1 how=$2 e=${served[0]}
  case $how in
    flip) python3 -c "import sys; p=sys.argv[1]; b=bytearray(open(p,'rb').read()); b[len(b)//2]^=1; open(p,'wb').write(b)" "$e" ;;
    foreign) cp "${served[1]}" "$e" ;;
    truncate) truncate -s 100 "$e" ;;
  esac
  run "$name" --cache "$url/lib-cache"; [[ $rc == 0 ]] || bad "$name: exit $rc"
  summary "$name" 's["cache"]["corrupt"] == 1 and s["cache"]["hits"] == 1 and s["cache"]["stored"] == 1'
  grep -q "corrupt cache entry, converting again: $url/lib-cache/v1/entries/.*: $3" "$work/$name.err" \
    || bad "$name: no warning naming the entry and '$3': $(cat "$work/$name.err")"
  same_as_reference "$name"
  cmp -s "$e" "$work/dircache/v1/entries/${e#"$work/srv/lib-cache/v1/entries/"}" || bad "$name: the entry was not stored anew"
}
damage flipped flip "checksum mismatch"
damage foreign foreign "stored under the wrong key"
damage truncated truncate "truncated"

# A writer killed half-way: nginx keeps nothing of an incomplete PUT.
key=$(basename "${served[0]}" .entry)
head -c 3000000 /dev/urandom >"$work/big"
curl -s -T "$work/big" --limit-rate 200k "$url/torn/v1/entries/${key:0:2}/$key.entry" & writer=$!
sleep 1; kill -9 $writer 2>/dev/null; wait $writer 2>/dev/null
sleep 0.5
[[ -e $work/srv/torn/v1/entries/${key:0:2}/$key.entry ]] && bad "a killed writer left an entry on the server"
status=$(curl -s -o /dev/null -w '%{http_code}' "$url/torn/v1/entries/${key:0:2}/$key.entry")
[[ $status == 404 ]] || bad "after a killed writer the entry answers $status, not 404"

# Read-only: reads, never writes.
run readonly --cache "$url/ro-cache" --cache-read-only; [[ $rc == 0 ]] || bad "read-only: exit $rc"
summary readonly 's["cache"]["stored"] == 0 and s["cache"]["hits"] == 0'
[[ -d $work/srv/ro-cache ]] && bad "read-only: the server got writes"
run readonly_warm --cache "$url/lib-cache" --cache-read-only; [[ $rc == 0 ]] || bad "read-only warm: exit $rc"
summary readonly_warm 's["cache"]["hits"] == 2'

# A local level in front: filled from the server, then enough on its own.
run local --cache "$url/lib-cache" --cache-local "$work/local"; [[ $rc == 0 ]] || bad "local: exit $rc"
summary local 's["cache"]["hits"] == 2'
[[ $(find "$work/local" -name '*.entry' | wc -l) == 2 ]] || bad "local: the local level was not filled"
run local_only --cache "http://127.0.0.1:$dead_port/x" --cache-local "$work/local"; [[ $rc == 0 ]] || bad "local only: exit $rc"
summary local_only 's["cache"]["hits"] == 2'
same_as_reference local_only

# A server that is down, answering 500, or silent: one warning, converted here, exit 0.
run down --cache "http://127.0.0.1:$dead_port/x" --cache-timeout 2; [[ $rc == 0 ]] || bad "down: exit $rc"
summary down 's["cache"]["hits"] == 0 and s["cache"]["stored"] == 0 and s["assets"]["lsnif"] == 2'
[[ $(grep -c 'cache server is unavailable' "$work/down.err") == 1 ]] || bad "down: not one warning: $(cat "$work/down.err")"
same_as_reference down
run broken --cache "$url/broken/x"; [[ $rc == 0 ]] || bad "500: exit $rc"
[[ $(grep -c 'cache server is unavailable.*HTTP 500' "$work/broken.err") == 1 ]] || bad "500: not one warning: $(cat "$work/broken.err")"
same_as_reference broken
silent_port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
python3 -c '
import socket, sys, time
s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("127.0.0.1", int(sys.argv[1]))); s.listen(16)
held = []
while True:
    c, _ = s.accept(); held.append(c)  # accepted, never answered
' "$silent_port" & silent_pid=$!
sleep 0.3
start=$(date +%s)
run silent --cache "http://127.0.0.1:$silent_port/x" --cache-timeout 1; [[ $rc == 0 ]] || bad "silent: exit $rc"
elapsed=$(($(date +%s) - start))
[[ $(grep -c 'cache server is unavailable.*(3 attempts)' "$work/silent.err") == 1 ]] || bad "silent: not one warning: $(cat "$work/silent.err")"
kill $silent_pid; silent_pid=
# Three attempts of 1 s and 0.75 s of pauses, once: the rest is conversion (a few seconds).
[[ $elapsed -lt 60 ]] || bad "silent: $elapsed s: the timeout is not bounded"
same_as_reference silent

# A token: without it writes are refused (one warning); with it they are stored; never shown.
run no_token --cache "$url/protected/c"; [[ $rc == 0 ]] || bad "no token: exit $rc"
summary no_token 's["cache"]["stored"] == 0'
[[ $(grep -c 'refused to store' "$work/no_token.err") == 1 ]] || bad "no token: not one warning: $(cat "$work/no_token.err")"
LSNIF_CACHE_TOKEN=s3cret-t0ken run token --cache "$url/protected/c"; [[ $rc == 0 ]] || bad "token: exit $rc"
summary token 's["cache"]["stored"] == 2'
LSNIF_CACHE_TOKEN=s3cret-t0ken "$lsnif" convert "$work/lib/ChineseDragon-10kv.off" -o "$work/token_convert" \
  --preset smoke --steps 40 --cache "$url/protected/c" >"$work/token_convert.out" 2>&1 || bad "token convert: exit $?"
if grep -rqa 's3cret-t0ken' "$work"/token* "$work/token_convert"; then bad "the token appears in an output, a log or an asset"; fi

# URLs that are no cache server: usage errors, and never a directory named after them.
for u in "ftp://127.0.0.1/x" "http://" "http://user:pw@127.0.0.1:$port/x" "s3://bucket/x" "http://127.0.0.1:$port/x?y=1" "http://127.0.0.1:99999/x"; do
  (cd "$work" && "$lsnif" batch lib -o "$work/badurl" --cache "$u" --preset smoke --steps 40 >/dev/null 2>"$work/badurl.err"); rc=$?
  [[ $rc == 2 ]] || bad "--cache $u: exit $rc (want 2)"
  grep -q "^error: --cache $u" "$work/badurl.err" || bad "--cache $u: $(cat "$work/badurl.err")"
done
[[ -e $work/http: || -e $work/ftp: || -e $work/s3: ]] && bad "a URL was taken for a directory"

# Two writers at once into one empty server path: both succeed, the entries are intact.
run two_a --cache "$url/two" & a=$!
run two_b --cache "$url/two" & b=$!
wait $a; ra=$?; wait $b; rb=$?
[[ $ra == 0 && $rb == 0 ]] || bad "two writers: exits $ra $rb"
run two_warm --cache "$url/two"; summary two_warm 's["cache"]["hits"] == 2 and s["cache"]["corrupt"] == 0'

# The server stopped mid-run, after the first store and before the last: the build goes on,
# with one warning, and its result is whole. A scaled copy of the armadillo is a third object
# (an exact copy would share the armadillo's conversion), so stores remain after the stop.
python3 - "$work/lib/armadillo.off" "$work/lib/armadillo_scaled.off" <<'PY'
import sys
lines = open(sys.argv[1]).read().split("\n")
counts = lines[1].split()
nv = int(counts[0])
for k in range(2, 2 + nv):
    lines[k] = " ".join(repr(float(x) * 1.25) for x in lines[k].split())
open(sys.argv[2], "w").write("\n".join(lines))
PY
"$lsnif" batch "$work/lib" -o "$work/stopped" --cache "$url/stopped" --preset smoke --steps 40 --threads 2 --json \
  >"$work/stopped.json" 2>"$work/stopped.err" & conv=$!
for _ in $(seq 600); do
  [[ $(entries stopped | wc -l) -ge 1 ]] && break
  sleep 0.1
done
stop_nginx
wait $conv; rc=$?
[[ $rc == 0 ]] || bad "server stopped mid-run: exit $rc"
summary stopped 's["assets"]["lsnif"] == 3 and s["assets"]["failed"] == 0'
stored=$(entries stopped | wc -l)
((stored >= 1 && stored < 3)) || bad "server stopped mid-run: $stored of 3 results reached it (the stop was not mid-run)"
[[ $(grep -c 'cache server is unavailable' "$work/stopped.err") == 1 ]] ||
  bad "server stopped mid-run: not one warning: $(cat "$work/stopped.err")"
rm "$work/lib/armadillo_scaled.off"

# The example server's rules (examples/cache-server/nginx.conf): anyone reads, the token writes.
sed -e "s#listen 8080;#listen 127.0.0.1:$port;#" -e "s#root /srv;#root $work/srv;#" \
    -e "s#CHANGE-ME#example-token#" -e "s#^pid .*#pid $work/example.pid;#" \
    -e "s#^worker_processes 2;#daemon off; master_process off; error_log $work/logs/example.err;#" \
    -e "s#access_log off;#access_log off; client_body_temp_path $work/logs/ebody;#" \
    "$project/examples/cache-server/nginx.conf" >"$work/example.conf"
"$nginx" -c "$work/example.conf" -p "$work" 2>>"$work/logs/start.err" & nginx_pid=$!
for _ in $(seq 50); do curl -s -o /dev/null "http://127.0.0.1:$port/" && break; sleep 0.1; done
entry=${served[1]}; rel=v1/entries/$(basename "$(dirname "$entry")")/$(basename "$entry")
code=$(curl -s -o /dev/null -w '%{http_code}' -T "$entry" "http://127.0.0.1:$port/lsnif-cache/$rel")
[[ $code == 403 ]] || bad "example server: a PUT without the token answered $code, not 403"
code=$(curl -s -o /dev/null -w '%{http_code}' -H 'Authorization: Bearer example-token' -T "$entry" "http://127.0.0.1:$port/lsnif-cache/$rel")
[[ $code == 201 || $code == 204 ]] || bad "example server: a PUT with the token answered $code"
code=$(curl -s -o "$work/fetched" -w '%{http_code}' "http://127.0.0.1:$port/lsnif-cache/$rel")
[[ $code == 200 ]] && cmp -s "$work/fetched" "$entry" || bad "example server: GET answered $code or other bytes"
LSNIF_CACHE_TOKEN=example-token run example --cache "http://127.0.0.1:$port/lsnif-cache"
[[ $rc == 0 ]] || bad "example server: exit $rc"
summary example 's["cache"]["hits"] == 1 and s["cache"]["stored"] == 1'
stop_nginx

[[ $fail == 0 ]] && echo "PASS: http cache"
exit $fail
