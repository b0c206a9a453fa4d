"""Paper Alg. 3, the real-time floor-plan update strategy, as collaborators that own their state.

- :mod:`.travel`: distance and turn travelled, obstruction, the mapped area (coverage);
- :mod:`.schedule`: when to register the plan next (``next_trigger``);
- :mod:`.judge`: accept / refine / reject a registration (a verdict; writes nothing);
- :mod:`.refiner`: the accepted plan's scale and its placement at the start;
- :mod:`.priors`: relocalisations on the accepted plan as gated floor-plan priors, their check;
- :class:`~frslam_graph.plan_updates.updater.FloorPlanUpdater`: the hook that routes the verdicts.
"""
