#!/usr/bin/env bash
# Create .venv with the CPU build of torch, the dataset reader (reader/: storage and schemas), datagen
# (editable, with test extras) and the osvp training package (osvp/, its own distribution).
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
# torch first and pinned: an unpinned torch pulls a multi-GB CUDA build.
python -m pip install -q "torch==2.13.0"
# One resolve for the three distributions of the checkout: datagen-reader (storage, schemas), the
# generator (datagen, needs the reader) and the osvp trainer (needs only the reader).
# -qq: errors only; setuptools' editable-install notice is printed once per package otherwise.
python -m pip install -qq -e ./reader -e ".[test]" -e "./osvp[test]"
