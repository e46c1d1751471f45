"""hydo's deploy side: run an exported policy on a Franka arm or its MuJoCo twin. Never imports torch.

Start reading at ``loop.py`` (the observe → decide → check → execute loop). The pieces, one home each:

    cell.py          the cell file (cameras, bin, workspace, limits), validated on load
    cameras.py       RealSense / twin / replay cameras behind one interface
    perception.py    background capture and subtraction -> segmented clouds in the base frame
    registration.py  goal clouds and current-to-goal registration (the goal flow)
    safety.py        the checks before any motion: inputs, workspace, kinematics, recovery rules
    arm.py           the Panda/FR3 MuJoCo model and IK (plan checks, the twin's arm)
    executor.py      the executor contract and its typed outcomes; panda.py, fr3.py, twin.py
    session_log.py   the session folder (fsynced JSONL + per-step arrays)
    fakes.py         scripted cameras and robot libraries for fault tests
    onnx_policy.py   the exported policy through onnxruntime
"""
