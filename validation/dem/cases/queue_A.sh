#!/usr/bin/env bash
# Grain calibration boxes, then the seed chute rerun with the binned
# stress / wall-force / width-resolved diagnostics (same deck and seeds
# as the stored reference, so the same trajectory).
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS=1
python calibration/run_calibration.py --autocommit > calibration/calibration.out 2>&1
python run_dem.py --workdir cases/seed --tflow 20 --autocommit > cases/seed.out 2>&1
