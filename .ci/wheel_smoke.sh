#!/usr/bin/env bash
# The tool as a user installs it: builds the sdist and, from it, the wheel (`python -m build`),
# installs the wheel in a fresh venv outside the checkout and runs it from an empty folder outside
# the checkout: `umad --version`, `umad graph check`, a short `umad eval` on one generated drive of
# 10 frames, and one bad input that must exit 2. A packaging regression (a file the verbs need left
# out of the wheel, a path relative to the repository, a top-level `operators` or `replay` module)
# fails here. About 2 minutes on 2 cores once pip's cache holds the dependencies.
#
# Usage: .ci/wheel_smoke.sh [BUILD_PYTHON]   (default: .venv/bin/python, which has `build` from the test extra)
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
build_python="${1:-$repo/.venv/bin/python}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

SECONDS=0
"$build_python" -m build --outdir "$work/dist" "$repo" > "$work/build.log" 2>&1 || { cat "$work/build.log"; exit 1; }
echo "built $(cd "$work/dist" && echo *) in ${SECONDS}s"
SECONDS=0
"${PYTHON:-python3}" -m venv "$work/venv"
"$work/venv/bin/pip" install -q --no-compile "$work"/dist/*.whl  # --no-compile: torch's .pyc files are made on import
echo "installed the wheel in a fresh venv in ${SECONDS}s"

cd "$work"
umad="$work/venv/bin/umad"
"$umad" --version
"$umad" graph check
"$work/venv/bin/python" -c "
import importlib.util
taken = [name for name in ('operators', 'replay') if importlib.util.find_spec(name)]
assert not taken, f'the wheel installs top-level modules {taken}; expected umad_operators and umad_replay'
"
SECONDS=0
"$umad" generate synthetic drives --normal 0 --anomalous 1 --frames 10 --workers 1 2> generate.log \
    || { cat generate.log; exit 1; }
"$umad" eval --data drives --out report > eval.log 2>&1 || { cat eval.log; exit 1; }
test -s report/index.html && test -s report/results.json
grep -Eq "^UMAD evaluation done in [0-9]+ s \(graph [0-9]+ s, sweep [0-9]+ s, report [0-9]+ s\)" eval.log \
    || { echo "eval's last line does not name its phases:"; tail -n 1 eval.log; exit 1; }
echo "generated one drive and evaluated it in ${SECONDS}s: $(tail -n 1 eval.log)"

status=0
"$umad" eval --data "$work/no-such-folder" --out refused 2> refused.log || status=$?
if [[ "$status" != 2 || -e refused ]] || ! grep -q "no-such-folder: no such folder or file; expected drives" refused.log; then
    echo "bad input: expected exit 2, one line and nothing written; got exit $status:" >&2
    cat refused.log >&2
    exit 1
fi
echo "wheel smoke test ok"
