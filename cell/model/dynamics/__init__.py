"""Dynamic models of the arm: physics (P1, P2), learned (D) and hybrid (H1-H3), behind one interface."""
