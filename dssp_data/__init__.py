"""The torch-free base every DSSP package stands on: the dataset format and the plumbing around it.

    replay_buffer  recording  attributes   the zarr dataset format (DP3 replay buffer + recording attributes)
    inspect view edit robotwin_hdf5 data_cli   ``dssp-data``: info, view, merge, split, convert, repair
    observation    the observation contract a model carries (point-cloud settings, state/action layout, rate)
    streaming_history   the one streaming state machine (recurrent state, the last N z tokens), numpy or torch
    errors  files  output_guard  schema  cli_runner   one-line errors, atomic files, owned outputs,
                                                       self-validating configs, the CLI runner

Imports numpy, zarr and numcodecs only; never torch or another DSSP package. Importing the package
loads nothing: import the module you need.
"""

