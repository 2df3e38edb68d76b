"""The GPU pair kernels compiled for an NVIDIA GPU on a machine without one: do they build, do
they spill, how many instructions a pair costs. A developer's check of the build, not a
benchmark: it times nothing (``benchmarks/gpu_session.sh`` measures the product on a GPU).

The Triton program of the JAX pair kernel (``pair_kernels.pair_program`` "triton", the two
Pallas kernels of ``affinebody._pair_triton``) runs only on a GPU, and a session is lent one
only now and then. This script takes the pair terms of ``run_scale.py``'s system (the one the
GPU figures of README are measured on; ``--all-families`` adds every pair family of the tests'
cases), lowers each kernel through Pallas' Triton lowering for CUDA as JAX does on a GPU
(``jax.export`` for the "cuda" platform), keeps the Triton module of each, and compiles it for
``--arch`` (default sm_90, an H100 or H200) with the ``triton`` package's own compiler and
``ptxas``, which need no GPU. For each kernel it prints the registers per thread, the stack
and local memory (a spill shows there), and the SASS instructions a thread runs (one pair per
thread): the total, the float64 ones (DFMA, DMUL, DADD), the global loads (LDG) and stores
(STG).

The ``triton`` package is not a dependency of the project (it is large, and JAX's GPU build
compiles the kernels with XLA's own Triton): give an interpreter that has it with
``--triton-python`` (a separate virtual environment), or install it where this runs.

    python3.11 -m venv /tmp/tri && /tmp/tri/bin/pip install triton
    .venv/bin/python tools/triton_offline.py --triton-python /tmp/tri/bin/python
    .venv/bin/python tools/triton_offline.py --triton-python /tmp/tri/bin/python \
        --all-families --keep /tmp/kernels        # + the .ttir, .ptx, .cubin and .sass files
    .venv/bin/python tools/triton_offline.py --triton-python /tmp/tri/bin/python \
        --batch 16                                # + vmapped over 16 systems (a sweep)

The figures are those of the ``triton`` package's compiler, not of the Triton inside XLA that
a GPU run uses: a check that the kernels compile and fit in registers, not a measurement of
their speed (``gpu_session.sh`` measures that on a GPU).
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))  # run_scale

#: Run by the interpreter that has ``triton``: compile each module named on the command line
#: for the target in argv[1] and write its .ptx and .cubin beside it.
COMPILE = """
import json, sys
import triton
from triton.backends.compiler import GPUTarget
arch, warps, paths = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3:]
for path in paths:
    kernel = triton.compile(path, target=GPUTarget("cuda", arch, 32),
                            options={"num_warps": warps, "num_stages": 1,
                                     "enable_fp_fusion": True})
    open(path + ".ptx", "w").write(kernel.asm["ptx"])
    open(path + ".cubin", "wb").write(kernel.asm["cubin"])
print(json.dumps({"triton": triton.__version__}))
"""

#: SASS opcodes counted apart: float64 arithmetic, global loads and stores.
FLOAT64 = ("DFMA", "DMUL", "DADD")


def pair_terms_of_the_benchmark():
    """[(label, pair term, n)] of run_scale.py's system, built by ``config.build``."""
    from run_scale import write_config

    from affinebody.config import build, load_config
    from affinebody.potentials.terms import PairTerm

    with tempfile.TemporaryDirectory() as tmp:
        built = build(load_config(write_config(Path(tmp), 6, steps=1, every=1)))
    n = built.state.phi.shape[-1]
    return [(f"run_scale ({type(t).__name__})", t, n) for t in built.system.potential.terms
            if isinstance(t, PairTerm)]


TESTS = Path(__file__).resolve().parents[1] / "tests"


def pair_terms_of_the_tests():
    """[(label, pair term, n)] of every case of tests/test_pair_kernels.py."""
    sys.path.insert(0, str(TESTS))
    from test_pair_kernels import CASES

    return [(label, potential, n) for label, (potential, n) in CASES.items()]


def triton_modules(potential, n: int, batch: int | None = None,
                   f_in_kernel: bool = False) -> list[str]:
    """The Triton modules (text) of the two kernels of one chunk (the scalars kernel, or with
    ``f_in_kernel`` the partials kernel; the rows kernel), lowered for CUDA by the tests'
    ``export_chunk_for_cuda`` (Pallas' lowering, kept as it passes); with ``batch`` vmapped
    over that many systems, as a sweep's samples run them."""
    from jax._src.pallas.triton import lowering

    sys.path.insert(0, str(TESTS))
    from test_pair_kernels import export_chunk_for_cuda

    modules = []
    lower = lowering.lower_jaxpr_to_triton_module

    def keeping(*args, **kwargs):
        result = lower(*args, **kwargs)
        modules.append(result.module.operation.get_asm(enable_debug_info=False))
        return result

    lowering.lower_jaxpr_to_triton_module = keeping
    try:
        export_chunk_for_cuda(potential, n, batch=batch, f_in_kernel=f_in_kernel)
    finally:
        lowering.lower_jaxpr_to_triton_module = lower
    return modules


def usage(cubin: Path, tools: Path) -> dict:
    """Registers, stack, local memory and the SASS instruction counts of one kernel."""
    resources = subprocess.run([str(tools / "cuobjdump"), "--dump-resource-usage", str(cubin)],
                               capture_output=True, text=True, check=True).stdout
    figures = {key.lower(): int(value) for key, value in
               re.findall(r"\b(REG|STACK|SHARED|LOCAL):(\d+)", resources)}
    sass = subprocess.run([str(tools / "cuobjdump"), "-sass", str(cubin)],
                          capture_output=True, text=True, check=True).stdout
    cubin.with_suffix(".sass").write_text(sass)
    opcodes = collections.Counter(
        match.group(1) for match in re.finditer(
            r"^\s+/\*[0-9a-f]{4}\*/\s+(?:@!?U?P[0-9T]\s+)?([A-Z0-9_]+)", sass, re.MULTILINE))
    figures.update(instructions=sum(opcodes.values()),
                   float64=sum(opcodes[op] for op in FLOAT64),
                   loads=opcodes["LDG"], stores=opcodes["STG"])
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--triton-python", default=sys.executable,
                        help="a Python with the triton package (default: this one)")
    parser.add_argument("--arch", type=int, default=90, help="compute capability (90: H100)")
    parser.add_argument("--all-families", action="store_true",
                        help="also every pair family of tests/test_pair_kernels.py")
    parser.add_argument("--keep", type=Path, help="keep the modules and binaries here")
    parser.add_argument("--batch", type=int, default=None,
                        help="also the kernels vmapped over this many systems (a sweep's "
                             "samples: a second grid axis)")
    args = parser.parse_args()

    try:
        tools = Path(subprocess.run(
            [args.triton_python, "-c", "import triton, pathlib; print(pathlib.Path("
             "triton.__file__).parent / 'backends' / 'nvidia' / 'bin')"],
            capture_output=True, text=True, check=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        raise SystemExit(f"{args.triton_python} has no triton package: make a virtual "
                         "environment with it (python3.11 -m venv /tmp/tri && /tmp/tri/bin/pip "
                         "install triton) and pass --triton-python /tmp/tri/bin/python") from None

    import jax

    jax.config.update("jax_enable_x64", True)
    from affinebody import _pair_triton

    terms = pair_terms_of_the_benchmark()
    if args.all_families:
        terms += pair_terms_of_the_tests()
    folder = args.keep or Path(tempfile.mkdtemp(prefix="triton_offline_"))
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, (label, potential, n) in enumerate(terms):
        for batch in (None,) if args.batch is None else (None, args.batch):
            tag = "" if batch is None else f" x{batch}"
            kernels = list(zip(("scalars", "rows"), triton_modules(potential, n, batch),
                               strict=True))
            if potential.columnwise:  # f in the first kernel (the product's, for such an f)
                kernels.append(("partials", triton_modules(potential, n, batch, True)[0]))
            for name, module in kernels:
                path = folder / f"{k:02d}-{name}{tag.replace(' x', '-batch')}.ttir"
                path.write_text(module)
                paths.append((label + tag, n, name, path))
    done = subprocess.run([args.triton_python, "-c", COMPILE, str(args.arch),
                           str(_pair_triton.WARPS), *(str(p[-1]) for p in paths)],
                          capture_output=True, text=True, check=False)
    if done.returncode:
        raise SystemExit(f"the triton compiler failed ({args.triton_python}):\n"
                         f"{done.stderr[-3000:]}")
    version = json.loads(done.stdout.strip().splitlines()[-1])["triton"]
    import jaxlib

    print(f"Pallas (JAX {jax.__version__}, jaxlib {jaxlib.__version__}) -> triton {version}, "
          f"sm_{args.arch}, {_pair_triton.WARPS} warps, {_pair_triton.BLOCK} pairs per "
          f"program (one per thread); per thread:")
    print(f"  {'pair term':<36} {'n':>2} {'kernel':<8} {'regs':>5} {'stack':>6} {'local':>6} "
          f"{'instr':>6} {'fp64':>5} {'LDG':>4} {'STG':>4}")
    for label, n, name, path in paths:
        f = usage(Path(str(path) + ".cubin"), tools)
        print(f"  {label:<36} {n:>2} {name:<8} {f['reg']:>5} {f['stack']:>6} {f['local']:>6} "
              f"{f['instructions']:>6} {f['float64']:>5} {f['loads']:>4} {f['stores']:>4}")
    if args.keep:
        print(f"modules, PTX, cubins and SASS in {folder}")


if __name__ == "__main__":
    main()
