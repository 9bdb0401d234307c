from fxcell.sim.ned2.server import main

raise SystemExit(main())
