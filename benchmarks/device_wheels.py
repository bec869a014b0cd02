"""Carry pobax's Python dependencies, as wheels, to a machine that cannot reach a package index (a lent GPU).

    python benchmarks/device_wheels.py fetch --to .whl [--python-version 3.12] [--skip-installed FILE] [--families ...]
    python3 benchmarks/device_wheels.py installed > FILE                          # there: what it holds already
    python3 benchmarks/device_wheels.py install --from .whl --target /tmp/site    # there; then PYTHONPATH=/tmp/site

`fetch` (here, where pip reaches the index) downloads the distributions that pobax imports: its command line, agents,
memories and evaluation, and one environment of each family named (`--families`, all by default: MuJoCo, pixel MuJoCo,
Craftax, NAVIX), found by importing them in a child process and mapping its modules to their distributions. Each is
taken at the version installed here, as a binary wheel for the other machine's Python on manylinux x86-64, without its
requirements (they are in the same list). JAX's own stack stays out (jax, jaxlib, numpy, scipy, ml_dtypes,
opt_einsum: the machine's accelerator build is kept), and so does every name in `--skip-installed FILE` (what
`installed` printed there: its distributions, `name==version` a line); `--only NAME ...` carries those alone. It prints
each wheel's size and the total, which travels with the working tree (the lent machines take 64 MiB a call in all).

`install` (there, with the standard library and pip alone) installs, of a folder of wheels, those whose distribution
the interpreter does not hold already, into `--target`, and prints their names; a distribution it holds keeps its
version. `installed` lists the interpreter's distributions.
"""

import argparse
import importlib.metadata as md
import json
import os
import re
import subprocess
import sys
from pathlib import Path

#: The accelerator's stack, which the other machine brings in its own build: never carried.
JAX_STACK = ("jax", "jaxlib", "numpy", "scipy", "ml-dtypes", "opt-einsum")
#: What installs pobax here and is not imported by it at run time, and pobax itself (it travels as source).
NEVER = ("pip", "setuptools", "wheel", "pobax-bench")
#: One environment of each optional family: importing the family and making it brings in what its steps need.
FAMILIES = {"mujoco": "Walker-V-v0", "pixels": "ant_pixels", "craftax": "craftax_pixels",
            "navix": "Navix-DMLab-Maze-01-v0"}
#: The platforms pip may take a binary wheel for (the lent machines: x86-64, glibc 2.17 and newer).
PLATFORMS = ("manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux_2_24_x86_64", "manylinux_2_27_x86_64",
             "manylinux_2_28_x86_64", "manylinux_2_31_x86_64", "manylinux_2_34_x86_64", "manylinux_2_35_x86_64",
             "manylinux1_x86_64", "manylinux_2_5_x86_64")

class Parser(argparse.ArgumentParser):
    """A command line it cannot read, or bad input, is one line on stderr and exit 2, as pobax's commands (the
    standard library's alone: `install` runs before pobax's requirements are there)."""

    def error(self, message: str):
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


_TRACE = """
import json, sys, importlib.metadata as md
import jax
import cli, pobax.agent, pobax.eval
from pobax.env import make
from pobax.memory._registry import MEMORIES, memory_class
for name in MEMORIES:  # a cell may import its library when built (the S6's memax)
    try:
        memory_class(name)(4, 4, key=jax.random.key(0))
    except TypeError:  # another constructor (Transformer-XL's): its imports are pobax's own
        pass
for env in sys.argv[1:]:
    make(env)
dists = md.packages_distributions()
names = {d for m in list(sys.modules) for d in dists.get(m.split(".")[0], [])}
print(json.dumps(sorted(names)))
"""


def canonical(name: str) -> str:
    """A distribution's name as the index compares names (PEP 503): lower case, runs of -_. as one -."""
    return re.sub(r"[-_.]+", "-", name).lower()


def wheel_name(path: str | Path) -> str:
    """The canonical distribution name of a wheel file (`NAME-VERSION-...whl`)."""
    return canonical(Path(path).name.split("-")[0])


def traced_distributions(families: tuple[str, ...], root: Path, p: Parser) -> list[str]:
    """The distributions whose modules a child process has loaded after importing pobax's command line, agents and
    evaluation and making one environment of each of `families` (on the CPU)."""
    envs = [FAMILIES[f] for f in families]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", _TRACE, *envs], cwd=root, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        p.error(f"importing pobax and {envs} failed here, so what it needs is unknown "
                f"({out.stderr.strip().splitlines()[-1] if out.stderr.strip() else out.returncode}): install its "
                f"extras first (pip install -e '.[all]')")
    return json.loads(out.stdout.strip().splitlines()[-1])


def plan(names: list[str], skip: set[str]) -> list[str]:
    """`name==version` of each of `names` to carry: at the version installed here, JAX's stack, pobax and `skip`
    (canonical names) left out."""
    leave = {canonical(n) for n in (*JAX_STACK, *NEVER)} | skip
    specs = []
    for n in sorted(names, key=canonical):
        if canonical(n) not in leave:
            specs.append(f"{n}=={md.version(n)}")
    return specs


def read_installed(path: Path, p: Parser) -> set[str]:
    """The canonical names of a file of `name==version` lines (what `installed` printed)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        p.error(f"--skip-installed {str(path)!r} cannot be read ({e}): give the file `installed` wrote on the "
                f"other machine")
    return {canonical(line.split("==")[0].strip()) for line in text.splitlines() if line.strip()}


def fetch(args, p: Parser) -> int:
    unknown = sorted(set(args.families) - set(FAMILIES))
    if unknown:
        p.error(f"--families {' '.join(unknown)}: no such family; choose from {', '.join(FAMILIES)}")
    skip = read_installed(args.skip_installed, p) if args.skip_installed else set()
    needed = traced_distributions(tuple(args.families), Path(__file__).resolve().parents[1], p)
    if args.only:
        by_name = {canonical(n): n for n in needed}
        strays = sorted({canonical(n) for n in args.only} - set(by_name))
        if strays:
            p.error(f"--only {' '.join(strays)}: not among what pobax imports here with --families "
                    f"{' '.join(args.families)}; choose from {' '.join(sorted(by_name))}")
        needed = [by_name[canonical(n)] for n in args.only]
    specs = plan(needed, skip)
    args.to.mkdir(parents=True, exist_ok=True)
    platform_flags = [f for name in PLATFORMS for f in ("--platform", name)]
    for spec in specs:
        name, version = spec.split("==")
        for old in args.to.glob("*.whl"):  # one version of each name: two stop the other machine's install
            if wheel_name(old) == canonical(name) and old.name.split("-")[1] != version:
                old.unlink()
        cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version",
               args.python_version, "--implementation", "cp", *platform_flags, "-d", str(args.to), spec]
        if subprocess.run(cmd, capture_output=True, text=True).returncode != 0:
            p.error(f"no wheel of {spec} for Python {args.python_version} on manylinux x86-64: install another "
                    f"version here, or leave it out with --skip-installed")
    total = 0
    for w in sorted(args.to.glob("*.whl")):
        total += w.stat().st_size
        print(f"{w.stat().st_size / 2**20:7.2f} MiB  {w.name}")
    print(f"{len(specs)} distributions, {total / 2**20:.1f} MiB in {args.to}")
    return 0


def installed(args, p: Parser) -> int:
    for name, version in sorted({(canonical(d.metadata["Name"]), d.version) for d in md.distributions()
                                 if d.metadata["Name"]}):
        print(f"{name}=={version}")
    return 0


def install(args, p: Parser) -> int:
    wheels = sorted(args.source.glob("*.whl"))
    if not wheels:
        p.error(f"--from {str(args.source)!r} holds no wheels (*.whl): run `fetch --to` into it first")
    have = {canonical(d.metadata["Name"]) for d in md.distributions() if d.metadata["Name"]}
    missing = [w for w in wheels if wheel_name(w) not in have]
    print(f"installing {len(missing)} of {len(wheels)} wheels: {' '.join(wheel_name(w) for w in missing)}")
    if missing:
        cmd = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
               "--no-cache-dir", "--upgrade", "--target", str(args.target), *map(str, missing)]
        return subprocess.run(cmd).returncode
    return 0


def main(argv=None) -> int:
    p = Parser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    f = sub.add_parser("fetch", help="download the wheels pobax needs (here)")
    f.add_argument("--to", type=Path, required=True, help="the folder of wheels (ignored by git; carried)")
    f.add_argument("--python-version", default="3.12", help="the other machine's Python (default: %(default)s)")
    f.add_argument("--families", nargs="*", default=list(FAMILIES), help="environment families (default: all)")
    f.add_argument("--skip-installed", type=Path, default=None, metavar="FILE",
                   help="what `installed` printed on the other machine: those distributions are not carried")
    f.add_argument("--only", nargs="+", default=None, metavar="NAME",
                   help="carry these of pobax's distributions alone (what the other machine lacks)")
    i = sub.add_parser("install", help="install the wheels the interpreter lacks (there)")
    i.add_argument("--from", dest="source", type=Path, required=True)
    i.add_argument("--target", type=Path, required=True, help="then export PYTHONPATH=TARGET")
    sub.add_parser("installed", help="list the interpreter's distributions, name==version a line (there)")
    args = p.parse_args(argv)
    return {"fetch": fetch, "install": install, "installed": installed}[args.command](args, p)


if __name__ == "__main__":
    sys.exit(main())
