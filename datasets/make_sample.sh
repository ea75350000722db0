#!/usr/bin/env bash
# Regenerate datasets/sample (images only) and datasets/binocular (observations
# only, with reconstruction frames), each with its truth beside it.
# Run from the repository root: bash datasets/make_sample.sh
set -euo pipefail
export OPENBLAS_NUM_THREADS=1
PY="${PYTHON:-python}"
[ -x .venv/bin/python ] && PY="${PYTHON:-.venv/bin/python}"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$PY" -m ari_sfm.simulate paper_single_images "$tmp" --image-scale 0.5 --seed 0
rm -rf datasets/sample
mv "$tmp/dataset" datasets/sample
mv "$tmp/truth.json" datasets/sample_truth.json
mv "$tmp/truth_observations.json" datasets/sample_truth_observations.json
du -sh datasets/sample

# binocular rig with translation-stage frames: corner pixels only (no images)
"$PY" -m ari_sfm.simulate binocular "$tmp/bino" --seed 0
rm -rf datasets/binocular
mv "$tmp/bino/dataset" datasets/binocular
mv "$tmp/bino/truth.json" datasets/binocular_truth.json
du -sh datasets/binocular datasets/binocular_truth.json
