"""What the C masked-Adam update (`recon_adam` in recon/nerf/march.c) costs a grid, as one revision builds it against
this checkout's, the two calls taken in turns.

    python benchmarks/adam_update_cost.py --base 07fed61 --out benchmarks/results/adam_update_cost.json

`--base`'s march.c is built as recon builds this checkout's (`native_step_cost.library_of`). Each round draws the
blocks a step flags (`--blocks` of the grid's 64-value blocks, in runs of one to three, scattered as a step's rays
scatter them; by default 26,208 of the 393,216 blocks of `fast`'s 128³×12 feature grid, what the half-res Lego's
steps flag after 600 steps) and gives both builds the same gradient there, each updating its own copy of one start,
one thread, the order alternating. The record gives each build's milliseconds a call (median of `--rounds`), the
ratio, and whether the two ended with the same values bit for bit. A measurement: it asserts nothing.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from native_step_cost import library_of  # noqa: E402  (through gpu_syncs, this checkout's recon comes first)


def main(argv: list[str] | None = None) -> int:
    from recon.app.bench import provenance
    from recon.atomic import write_json_atomic
    from recon.nerf.native import ADAM_BLOCK, adam_blocks, native_marcher

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", required=True, help="the git revision whose march.c is measured against this one")
    parser.add_argument("--shape", default="2097152,12", help="the grid parameter's shape (rows, channels)")
    parser.add_argument("--blocks", type=int, default=26208, help="blocks flagged a call")
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if native_marcher() is None:
        print("error: the native library is not loaded here (no C compiler, or RECON_NATIVE=0)", file=sys.stderr)
        return 2
    row = {"name": "adam_update_cost", "base": args.base, "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
           **provenance(), "load_average_start": [round(x, 2) for x in os.getloadavg()]}
    shape = tuple(int(x) for x in args.shape.split(","))
    n = shape[0] * shape[1]
    blocks = adam_blocks(n)
    with tempfile.TemporaryDirectory() as tmp:
        libs = {"base": library_of(args.base, Path(tmp)), "this": native_marcher()}
        g = torch.Generator().manual_seed(0)
        start = torch.randn(n, generator=g)
        state = {name: [start.clone(), torch.zeros(n), torch.zeros(n), torch.zeros(n)] for name in libs}
        for values in state.values():  # every page written once, as a trained grid's are
            for t in values[1:]:
                t.fill_(1.0).zero_()
        times: dict[str, list[float]] = {name: [] for name in libs}
        whole = n // ADAM_BLOCK  # blocks a run may start in whole
        for r in range(args.rounds):
            starts = torch.randint(0, whole - 3, (args.blocks,), generator=g)
            runs = torch.randint(1, 4, (args.blocks,), generator=g)
            flagged = torch.unique(torch.cat([starts + k for k in range(3)])[torch.cat([runs > k for k in range(3)])])
            flagged = flagged[: args.blocks]
            grad = torch.randn(len(flagged), ADAM_BLOCK, generator=g) * (torch.rand(len(flagged), ADAM_BLOCK,
                                                                                   generator=g) < 0.6)
            t = r + 1
            order = list(libs) if r % 2 == 0 else list(reversed(libs))
            for name in order:
                param, grad_buf, exp_avg, exp_avg_sq = state[name]
                grad_buf[: whole * ADAM_BLOCK].view(whole, ADAM_BLOCK)[flagged] = grad
                flags = torch.zeros(blocks, dtype=torch.uint8)
                flags[flagged] = 1
                t0 = time.perf_counter()
                libs[name].recon_adam(n, param.data_ptr(), grad_buf.data_ptr(), exp_avg.data_ptr(),
                                      exp_avg_sq.data_ptr(), 0.1, 0.99, 1.0 - 0.99, 0.01 / (1 - 0.9**t),
                                      (1 - 0.99**t) ** 0.5, 1e-15, 1, 1, flags.data_ptr())
                times[name].append(time.perf_counter() - t0)
        same = all(torch.equal(a, b) for a, b in zip(state["base"], state["this"], strict=True))
    ms = {name: round(1000 * statistics.median(v), 3) for name, v in times.items()}
    row.update({"shape": list(shape), "blocks_flagged": args.blocks, "blocks": blocks, "rounds": args.rounds,
                "threads": 1, "ms_per_call_median": ms, "this_vs_base": round(ms["this"] / ms["base"], 3),
                "same_values_bit_for_bit": same})
    write_json_atomic(args.out, [row])
    print(f"recon_adam on {shape}, {args.blocks:,} of {blocks:,} blocks flagged: {args.base} {ms['base']} ms, this "
          f"checkout {ms['this']} ms ({row['this_vs_base']}x); the same values bit for bit: {same}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
