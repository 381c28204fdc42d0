"""The model lab: collect excitation data, train, evaluate and tune the dynamic models, and import
another robot's logs as a dataset."""
