"""The dataset: DP3's zarr format, what a recording adds to it, and ``dssp-data`` (torch-free).

    replay_buffer  recording  attributes   the zarr dataset format (DP3 replay buffer + recording attributes)
    inspect view edit robotwin_hdf5 data_cli   ``dssp-data``: info, view, merge, split, convert, repair
    observation    the observation contract a model carries (point-cloud settings, state/action layout, rate)
    streaming_history   the one streaming state machine (recurrent state, the last N z tokens), numpy or torch
    rerun_views  arm_kinematics   Rerun views of a tick, the Piper's forward kinematics (robot and simulation)
    bounded        bounded decoding of stored chunks

The plumbing every command shares (errors, atomic files, the output guard, schemas, the CLI runner) is
:mod:`dssp_core`, below this package.

Imports numpy, zarr, numcodecs and dssp_core only; never torch or another DSSP package. Importing the package
loads nothing: import the module you need.
"""
