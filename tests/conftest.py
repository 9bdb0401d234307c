pytest_plugins = ["fxcell.testing", "pytester"]
