#!/usr/bin/env bash
# A wheel built from this checkout, installed in a fresh venv, run from outside the checkout:
# the packaged DBC, --version, check-dbc, compile, identify, track and a2l must work without the source tree.
set -euo pipefail
REPO="$(cd "$(dirname "$0")/../.." && pwd)"
PY="$REPO/.venv/bin/python"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
# build from a copy of the checkout's files (tracked and new, not ignored): setuptools would otherwise
# leave a build/ tree in the checkout, and a stale one can put deleted modules into the next wheel
mkdir "$WORK/src"
git -C "$REPO" ls-files -co --exclude-standard -z | (cd "$REPO" && tar --null --ignore-failed-read -T - -cf - 2>/dev/null) | tar -xf - -C "$WORK/src"
"$PY" -m pip wheel -q --disable-pip-version-check --no-deps -w "$WORK/dist" "$WORK/src"
python3 -m venv "$WORK/venv"
"$WORK/venv/bin/python" -m pip install -q --disable-pip-version-check "$WORK"/dist/*.whl
cd "$WORK"                                   # nothing of the checkout on the path from here
"$PY" -m sim_bench simulate --out "$WORK/a.csv" --nu 17.2 --lh-um 3.3 > /dev/null
"$PY" -m sim_bench simulate --out "$WORK/b.csv" --nu 17.2 --lh-um 3.3 > /dev/null
BIN="$WORK/venv/bin"
"$BIN/injector-estimator" --version
"$BIN/injector-estimator" check-dbc | grep -q "ok -" || { echo "check-dbc failed"; exit 1; }
"$BIN/injector-estimator" dbc-path | grep -q "site-packages/estimator/dbc/injector.dbc" || { echo "dbc-path"; exit 1; }
"$BIN/python" -c "import estimator.codec.database as d, sys; p = d.default_dbc_path(); \
assert 'site-packages' in str(p) and p.exists(), p; print('packaged DBC:', p)"
"$BIN/injector-estimator" compile            # the numba cache beside the installed sources, two processes
"$BIN/injector-estimator" compile 2>&1 | grep -q "already cached" || { echo "compile did not mark the cache"; exit 1; }
"$BIN/injector-estimator" identify "$WORK/a.csv" --json | "$BIN/python" -c "import json, sys; d = json.load(sys.stdin); \
assert d['status'] in ('ok', 'uncertain') and abs(d['lh_um'] - 3.3) < 0.2, d; print('identify:', d['status'], d['lh_um'])"
"$BIN/injector-estimator" track "$WORK/a.csv" "$WORK/b.csv" | wc -l | grep -q 2
"$BIN/injector-sim" --version > /dev/null
"$BIN/injector-estimator" a2l --help > /dev/null   # the XCP slave's A2L, written by the installed package
"$BIN/injector-estimator" a2l --out "$WORK/x.a2l" | grep -q "A2L for the XCP slave" || { echo "a2l failed"; exit 1; }
grep -q "/begin CHARACTERISTIC ident.sigma_limit_lh_um" "$WORK/x.a2l" || { echo "a2l: no characteristics"; exit 1; }
echo "install check: ok (wheel $(basename "$WORK"/dist/*.whl))"
