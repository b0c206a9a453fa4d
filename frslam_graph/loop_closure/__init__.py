"""Loop closure: the closer hook (:mod:`.closer`: candidates, verification, pairwise confirmation,
pruning), scan-to-submap matching (:mod:`.submap_matching`) and the dense alignment between passes
at the end of a run (:mod:`.final_alignment`)."""
