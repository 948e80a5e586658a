"""`v2vsim train`: stages of the LiDAR zoo (docs/training.md): the single-agent model, a cache of
its frozen encoder's features, early fusion, and every intermediate fusion method on the cache."""
