"""The core every DSSP package stands on: what each command needs whatever it does.

    errors        one-line errors (DSSPError and its kinds): what is wrong and what to do
    files         atomic file writes and directory swaps, folders made for an output, metadata read without links
    output_guard  one rule for every output path: what a command may write or replace (OutputKind, OutputDir)
    staging       outputs built beside their place and put there whole; one writer per output; Ctrl-C at safe points
    schema        typed settings files that validate themselves
    cli_runner    the commands' runner: one-line errors, Ctrl-C, warnings
    machine       the machine a figure was measured on

The standard library and numpy only; never torch, zarr or another DSSP package. Each command declares the
output kinds it writes next to itself (``RUN_DIR`` in ``dssp_train.cli.train``, ``DATA_DATASET`` in
``dssp_data.edit``, …). Importing the package loads nothing: import the module you need.
"""
