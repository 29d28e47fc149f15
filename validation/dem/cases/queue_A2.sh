#!/usr/bin/env bash
# h_stop ramps (rerun after the gravity-change fix), then the seed chute rerun with diagnostics.
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS=1
python calibration/run_calibration.py --autocommit --only hstop_220 hstop_160 hstop_110 hstop_070 hstop_040 > calibration/calibration_hstop.out 2>&1
python run_dem.py --workdir cases/seed --tflow 20 --autocommit > cases/seed.out 2>&1
