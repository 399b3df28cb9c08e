"""`symfunnel tune`: the search for design parameters that keep the funnels within the torque limit (derivative-free
over the sampled loop, or IPOPT with CVODES sensitivities over the continuous one), checked by verify's gate."""
