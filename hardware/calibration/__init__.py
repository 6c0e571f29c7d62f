"""Hand-eye calibration of the camera with a ChArUco board (``dssp-calibrate``).

Modules, in the order a calibration runs them:

- ``pose_plan``: the poses (N, 6) rad, from a JSON file or generated around the arm's start, inside the limits, and
  refused before the arm moves when they could not pass the solve (``check_plan``);
- ``tour``: ``CalibrationTour``, the control loop's policy source that visits them through the safety layer, waits
  until the arm is still and keeps a colour frame of each (``View``);
- ``charuco``: the board (``CharucoBoardSpec``, its image) and its pose in a frame (``detect_board``);
- ``hand_eye``: the solve with OpenCV's methods, the residuals per view, and the refusals (``solve_hand_eye``;
  ``PoseSpread``: what a set of poses must give the solve, for a plan and for the views alike).

Frames: the camera's optical frame (x right, y down, z forward), the robot's base frame, the gripper = the Piper's
flange (DH frame 6, :func:`dssp_data.arm_kinematics.flange_pose`), the board frame (OpenCV's). Transforms are (4, 4)
float64, metres, named ``a_to_b`` (a point in a -> the same point in b).
"""
