"""The arm's models: robot specs by name, the nominal Pinocchio model, and the dynamic models
(physics, learned, hybrid) of the joint torques."""
