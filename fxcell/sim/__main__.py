from fxcell.sim.cli import main

raise SystemExit(main())
