import os

from hypothesis import settings

pytest_plugins = ["fxcell.testing", "pytester"]

# CI runs the property tests on fixed examples (a red CI run always reproduces); developers'
# runs keep exploring new ones (`FXCELL_HYPOTHESIS=explore` forces that in CI too).
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI") and os.environ.get("FXCELL_HYPOTHESIS") != "explore":
    settings.load_profile("ci")
