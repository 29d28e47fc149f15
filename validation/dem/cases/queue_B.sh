#!/usr/bin/env bash
# Variants of the seed chute for the validation of the nonlocal model:
# grain-sidewall friction 0.15 (26 deg), then the 27 deg slope (mu_w 0.3).
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS=1
python run_dem.py --workdir cases/muw015 --tflow 20 --autocommit --var mu_w 0.15 > cases/muw015.out 2>&1
python run_dem.py --workdir cases/theta27 --tflow 20 --autocommit --var theta 27.0 > cases/theta27.out 2>&1
