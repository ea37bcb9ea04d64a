"""Measuring the system: visibility metrics (`metrics`), the attacks pictures meet on the way to the
web (`attacks`), test-split evaluation as training validates and as `meshseal detect` reads
(`evaluate`), `meshseal embed`'s report and preview sheets (`reports`), and the paper re-run's
plan (`paper_plan`)."""
