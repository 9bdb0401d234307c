from fxcell.cli import main

raise SystemExit(main())
