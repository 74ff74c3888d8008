#!/usr/bin/env bash
# The test command (README and CI): the whole suite under a virtual X display.
#
# napari needs a real X display even for a hidden viewer (QT_QPA_PLATFORM=offscreen gives no OpenGL
# context), so the suite runs under xvfb-run with Qt's default xcb platform. Where Xvfb or the xcb
# libraries Qt loads are missing, they are installed first with apt-get (as root, or through sudo).
# Before pytest: ruff and the import-layer contracts (lint-imports). Arguments go to pytest, e.g. `bash scripts/test.sh -k napari`. PYTHON overrides the interpreter
# (default .venv/bin/python).
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-.venv/bin/python}"

PACKAGES=(xvfb xauth libgl1 libegl1 libfontconfig1 libdbus-1-3 libxkbcommon-x11-0 libxcb-icccm4 libxcb-image0
          libxcb-keysyms1 libxcb-randr0 libxcb-render-util0 libxcb-shape0 libxcb-xfixes0 libxcb-xinerama0
          libxcb-xkb1 libxcb-cursor0)

missing=()
if command -v dpkg-query >/dev/null 2>&1; then
    for p in "${PACKAGES[@]}"; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing+=("$p")
    done
elif ! command -v xvfb-run >/dev/null 2>&1; then
    echo "scripts/test.sh: xvfb-run not found and this is not a Debian/Ubuntu system: install Xvfb, then rerun" >&2
    exit 1
fi
if [ "${#missing[@]}" -gt 0 ]; then
    echo "scripts/test.sh: installing ${missing[*]} (napari's Qt tests need an X server)" >&2
    if [ "$(id -u)" -eq 0 ]; then sudo=(); elif command -v sudo >/dev/null 2>&1; then sudo=(sudo); else
        echo "scripts/test.sh: not root and no sudo: install them with apt-get, then rerun" >&2; exit 1; fi
    "${sudo[@]}" apt-get update -qq
    "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# Static checks first (docs/architecture.md): lint and import order, then the layer contracts.
BIN="$(dirname "$PYTHON")"
"$PYTHON" -m ruff check --quiet .
"$BIN/lint-imports" --no-cache >/dev/null || { "$BIN/lint-imports" --no-cache; exit 1; }

# Qt binding: napari's default, PyQt6 (the test extra installs it through napari[qt]); QT_API=pyqt5 runs the same
# tests on PyQt5 where it is installed (pip install pyqt5).
if [ -z "${QT_API:-}" ] && "$PYTHON" -c "import PyQt6.QtCore" >/dev/null 2>&1; then export QT_API=pyqt6; fi

exec xvfb-run -a -s "-screen 0 1280x1024x24" "$PYTHON" -m pytest -q "$@"
