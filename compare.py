"""Compare evaluate.py / train.py output folders: tables, overlaid curves, report.html (docs/compare.md).

python compare.py OUT1 OUT2 ... [--names a b ...] [--out DIR] [--allow-different-pairs] [--n-examples 4]
python compare.py SWEEP_DIR     # the runs 0/, 1/, ... of an evaluate.py -m sweep
"""

import sys

if __name__ == "__main__":
    from shapecorr.cli.compare import main

    sys.exit(main())
