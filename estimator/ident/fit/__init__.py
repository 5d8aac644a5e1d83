"""The single-injection fit: N_u and L_h from one injection's current and voltage (eq. 28), its cost
functions, searches, compiled local fits, judgement of the model, and the bound it is measured against."""
