/* The Lienard plant of the paper's Section V (plants/lienard.py) and classical RK4. */
#include "plant.h"

#include <math.h>

static void rhs(const lienard *p, const double x[PLANT_N], const double u[PLANT_M], double dx[PLANT_N]) {
    double x1 = x[0], x1sq = x1 * x1;
    dx[0] = x[1] + x1 + p->a * x1 * x1sq - p->b * x1 * x1sq * x1sq;
    dx[1] = -x1 + u[0];
}

long rk4_substeps(double T) {
    double n = ceil(T / RK4_H_MAX - 1e-9);
    return n < 1 ? 1 : (long)n;
}

int lienard_flow(const lienard *p, double x[PLANT_N], const double u[PLANT_M], double T) {
    long n = rk4_substeps(T);
    double h = T / (double)n;
    double k1[PLANT_N], k2[PLANT_N], k3[PLANT_N], k4[PLANT_N], y[PLANT_N], next[PLANT_N];
    for (long s = 0; s < n; s++) {
        int i;
        rhs(p, x, u, k1);
        for (i = 0; i < PLANT_N; i++) y[i] = x[i] + 0.5 * h * k1[i];
        rhs(p, y, u, k2);
        for (i = 0; i < PLANT_N; i++) y[i] = x[i] + 0.5 * h * k2[i];
        rhs(p, y, u, k3);
        for (i = 0; i < PLANT_N; i++) y[i] = x[i] + h * k3[i];
        rhs(p, y, u, k4);
        double big = 0.0;
        for (i = 0; i < PLANT_N; i++) {
            next[i] = x[i] + (h / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
            double a = fabs(next[i]);
            big = a > big || a != a ? a : big;
        }
        if (!(big <= p->x_max)) return FLOW_DIVERGED; /* NaN too: x keeps the last good state */
        for (i = 0; i < PLANT_N; i++) x[i] = next[i];
    }
    return FLOW_OK;
}
