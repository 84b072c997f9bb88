"""Analysis of the paper's results: Theorem 1 and 2 bounds, region of attraction, empirical DoS tolerance.

Pure numerics (numpy, scipy and the batch simulator); figures with matplotlib's
Agg backend, imported only when drawing.

* :mod:`.theorem1`: phi_0, phi_1, P_0, P_1, mu_0, mu_1, nu_0, nu_1, condition
  (stability), the allowable (rho_D, rho_F) region, optimized over the free choices;
* :mod:`.theorem2`: c_0, c_1, gamma_0, gamma_1, d, delta, alpha, beta, omega_0,
  omega_1 and the E_0 bound of (convergence);
* :mod:`.lmi`: the small LMI solver the optimization uses;
* :mod:`.roa`: nominal region of attraction on a grid;
* :mod:`.sweep`: empirical tolerance over (rho_F, rho_D) and vulnerable initial states;
* :mod:`.summary`: scenario-level analysis (``testbed analyze``);
* :mod:`.figures`: the PNG figures; :mod:`.cli`: ``testbed analyze | roa | sweep``.
"""

from .region import Region, allowable_region, analyze_theorem1
from .theorem1 import Certificate, Loop, plain_certificate, stability_lhs
from .theorem2 import RemainderRadius, lemma_constants, theorem2, theorem2_auto

__all__ = ["Loop", "Certificate", "Region", "allowable_region", "analyze_theorem1", "plain_certificate",
           "stability_lhs", "RemainderRadius", "lemma_constants", "theorem2", "theorem2_auto"]
