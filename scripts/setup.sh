#!/usr/bin/env bash
# Create .venv with the CPU build of torch, datagen (editable, with test extras) and the osvp training
# package beside it (osvp/, its own distribution; it needs the root's storage and schemas).
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
# torch first and pinned: an unpinned torch pulls a multi-GB CUDA build.
python -m pip install -q "torch==2.13.0"
python -m pip install -q -e ".[test]"
python -m pip install -q -e "./osvp[test]"
