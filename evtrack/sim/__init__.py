"""The synthetic data engine: renders, events, blurred RGB-D and ground truth."""
