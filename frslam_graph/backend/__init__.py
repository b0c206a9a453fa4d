"""The backend's parts: the context the hooks see, the keyframe store, the decision log, the
deferred steps, the pose graph, the FRSlam facade and the offline run (see each module)."""
