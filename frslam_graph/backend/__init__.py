"""The backend's state and its lower layer (below the hooks and the facade).

- :mod:`.context`: ``BackendContext``, what the hooks see, and the ``BackendHook`` protocol;
- :mod:`.keyframes`: the keyframe store and the per-scan track;
- :mod:`.decisions`: the decision log (one typed event per decision);
- :mod:`.deferred`: deferred steps with the per-scan budget;
- :mod:`.graph`: the pose graph (iSAM2, priors, LM batches);
- :mod:`.mapping`: occupancy mapping of the keyframe scans.

The facade that builds them is :mod:`frslam_graph.slam` (``FRSlam``); the offline run is
:mod:`frslam_graph.offline`.
"""
