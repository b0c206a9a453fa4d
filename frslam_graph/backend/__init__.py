"""The SLAM backend, in the order a scan goes through it.

- :mod:`.slam`: ``FRSlam``, the composition root and facade (scans in, pose / ``map_to_odom``
  out, ``finish``); the per-scan core step;
- :mod:`.context`: ``BackendContext``, what the hooks see, and the ``BackendHook`` protocol;
- :mod:`.keyframes`: the keyframe store and the per-scan track;
- :mod:`.decisions`: the decision log (one typed event per decision);
- :mod:`.deferred`: deferred steps with the per-scan budget; :mod:`.steps`: step generators;
- :mod:`.graph`: the pose graph (iSAM2, priors, LM batches);
- :mod:`.mapping`: occupancy mapping of the keyframe scans;
- :mod:`.offline`: the offline run over a recording, its outputs and evaluation.
"""
