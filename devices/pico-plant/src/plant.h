/* The plant of the paper's example and its fixed-step integrator. */
#ifndef PICO_PLANT_PLANT_H
#define PICO_PLANT_PLANT_H

#define PLANT_N 2
#define PLANT_M 1

/* flow_status codes of PlantTelemetry (docs/protocol.md) */
#define FLOW_OK 0
#define FLOW_DIVERGED 1

/* the longest substep of the integrator, in seconds (docs/devices.md says how it was chosen) */
#define RK4_H_MAX 1e-3

typedef struct {
    double a, b;        /* Lienard: x1' = x2 + x1 + a x1^3 - b x1^5, x2' = -x1 + u */
    double x_max;       /* ||x||_inf above this: FLOW_DIVERGED ([flow] x_max) */
} lienard;

/* x <- phi_T(x, u) by classical RK4 with ceil(T / RK4_H_MAX) equal substeps. Returns a flow status;
 * on FLOW_DIVERGED x is the last substep's state that was finite and within x_max. */
int lienard_flow(const lienard *p, double x[PLANT_N], const double u[PLANT_M], double T);
/* the number of substeps lienard_flow takes over T */
long rk4_substeps(double T);

#endif
