"""The thermal model of a brake block: physics of the heat input (eqs. 1-12), the declared
model's effects, the finite-element model (Rust core), its reduced model, and the simulation of a
timeline of inputs. Knows the fleet, not the warehouse."""
