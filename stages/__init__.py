"""Pipeline stages: one module per stage, each with NAME, VERSION, ARTIFACT, INPUTS, Params, run() and main()."""
