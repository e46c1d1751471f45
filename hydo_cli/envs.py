"""Env construction, one home for training, evaluation and export: an object set or task → envs."""

from __future__ import annotations

from hydo_cli.errors import HydoError


def make_envs(
    objects,
    goals,
    clutter,
    obs,
    n_envs,
    n_obj=None,
    n_bg=None,
    render=False,
    task=None,
    task_start="fixed",
    flip_share=None,
    contacts="hydo",
):
    """``n_envs`` envs of one configuration (point counts default to the contract's).

    ``task`` (``sim.tasks``) replaces objects, goals and clutter by the task's scene; ``task_start``
    is ``fixed`` (evaluation) or ``random`` (training). ``flip_share``: training's mix of 6D goals
    (``BinEnv``). ``contacts``: the scene's contact model (``sim.contract.CONTACT_MODELS``, set by
    ``sim.scene``).
    """
    from sim.contract import DEFAULT_N_BG, DEFAULT_N_OBJ
    from sim.env import BinEnv
    from sim.objects import ObjectMeshError, load_objects

    if task is None:
        try:
            assets = load_objects(objects)
        except ObjectMeshError:
            raise
        except ValueError as e:  # an unknown split or object name: say which forms are valid
            raise HydoError(str(e)) from None
    else:
        assets = "cube"  # unused: the task names its object
    return [
        BinEnv(
            objects=assets,
            goals=goals,
            obs=obs,
            clutter=0 if task else clutter,
            n_obj=n_obj or DEFAULT_N_OBJ,
            n_bg=n_bg or DEFAULT_N_BG,
            render_mode="rgb_array" if render else None,
            task=task,
            task_start=task_start,
            flip_share=flip_share,
            contacts=contacts,
        )
        for _ in range(n_envs)
    ]
