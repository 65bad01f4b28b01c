"""Steps 4-5: semantic entropy and the adaptive kernel length."""
import taichi as ti


@ti.func
def normalized_entropy(p, num_real: ti.template()):
    """Shannon entropy of the unnormalised vector p over classes 1..C-1, divided by log(C-1).

    Class 0 (unlabeled) never receives evidence, so it is left out of the support: a voxel
    with uniform evidence over the 19 real classes gets exactly 1.
    """
    total = 0.0
    for c in ti.static(range(1, num_real + 1)):
        total += p[c]
    h = 0.0
    for c in ti.static(range(1, num_real + 1)):
        q = p[c] / total
        if q > 0:
            h -= q * ti.log(q)
    return h / ti.log(ti.cast(num_real, ti.f32))


@ti.func
def adaptive_length(p, ell_min, ell_max, num_real: ti.template()):
    """L(v) = L_min + (L_max - L_min) * normalised entropy of p(c|v)."""
    return ell_min + (ell_max - ell_min) * normalized_entropy(p, num_real)
