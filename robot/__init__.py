"""hydo's deploy side: run an exported policy on a Franka arm or its MuJoCo twin. Never imports torch.

Start reading at ``loop.py`` (the observe → decide → check → execute loop). The pieces, one home each:

    loop.py          the deploy loop: start-up checks, episodes, steps, refusals
    recovery.py      what happens after a plan that did not end ok: stop, recover, retract
    report.py        step / episode / session records, the summary table and summary.json
    twin_metrics.py  twin only: masks, registration and distance against the true poses
    cell.py          the cell file (cameras, bin, workspace, limits), validated on load
    cameras.py       the camera interface: RealSense and session replay
    connect.py       builds the executor for --robot and the cell's cameras (the only place that
                     picks panda.py, fr3.py or twin.py)
    perception.py    background capture and subtraction -> segmented clouds in the base frame
                     (the pure depth pipeline of sim.depth; never the MuJoCo renderer)
    registration.py  goal clouds and current-to-goal registration (the goal flow)
    safety.py        the checks before any motion: inputs, workspace, kinematics, recovery rules
    arm.py           the Panda/FR3 MuJoCo model and IK (plan checks, the twin's arm)
    executor.py      the executor contract and its typed outcomes
    libfranka.py     libfranka's error vocabulary and flange frame, shared by panda.py and fr3.py
    panda.py         the Panda through panda-python
    fr3.py           the FR3 through franky
    twin.py          the MuJoCo twin: world, rendered cameras, executor, episodes (sim.goals)
    session_log.py   the session folder (fsynced JSONL + per-step arrays)
    onnx_policy.py   the exported policy through onnxruntime

Test doubles (scripted cameras, fake robot libraries) live in ``tests/robot/fakes.py``.
"""
