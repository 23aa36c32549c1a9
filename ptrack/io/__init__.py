"""What a run writes besides result.npz: BVH export and the rerun log (viewer). Imports `body` and
`observe` only, so the pipeline can write through it."""
