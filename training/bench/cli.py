"""``pranet-bench`` (see the package docstring)."""

from __future__ import annotations

import json
import shlex
import sys
from collections.abc import Sequence

from pranet.training.bench.catalog import BREAKDOWN_PAIRS
from pranet.training.bench.report import _json_default, breakdown, report
from pranet.training.bench.run import log, parse_args, run
from pranet.training.reporting import nan_to_none


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["scans"]:  # the real-scan benchmark (training.bench.scans), a subcommand of its own
        from pranet.training.bench.scans import main as scans_main

        return scans_main(argv[1:])
    args = parse_args(argv)
    command = shlex.join(["pranet-bench", *argv])
    result = run(args, command)
    result["breakdown"] = {
        f"{a} / {b}": breakdown(result["records"], args.settings, a, b)
        for a, b in BREAKDOWN_PAIRS
        if a in args.methods and b in args.methods
    }
    text = report(result)
    print(text)
    if args.markdown is not None:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(f"```\n{command}\n```\n\n{text}")
        log(args, f"wrote {args.markdown}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        doc = json.loads(json.dumps(result, default=_json_default))  # records -> dicts first
        args.json.write_text(json.dumps(nan_to_none(doc), indent=1))
        log(args, f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
