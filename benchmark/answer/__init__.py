"""The main job: each method's cheapest setting that stands at each target, by search, and paired timing of the contenders."""
