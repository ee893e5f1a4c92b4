"""``python -m kikuchipy_geomdic``: the command line."""

from kikuchipy_geomdic.cli import main

raise SystemExit(main())
