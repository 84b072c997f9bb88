/* The join file (docs/protocol.md, "Joining a run from outside") and the scenario it embeds:
 * what the plant device reads of them, every field checked. */
#ifndef PICO_PLANT_JOIN_H
#define PICO_PLANT_JOIN_H

#include <stddef.h>
#include <stdint.h>

#include "plant.h"

#define JOIN_MAX_BYTES (1 << 20)
#define MAX_ENDPOINTS 8
#define MAX_WAIT 8

typedef struct {
    char run_id[128];
    char prefix[160];            /* testbed/<run_id> */
    char connect[MAX_ENDPOINTS][256];
    int n_connect;
    int mutual_tls;              /* credentials.kind mutual_tls; else none (plain TCP) */
    char ca[1024], cert[1024], key[1024];
    int64_t T_ns;
    uint32_t n_steps;
    char digest[17];
    int ack_via_attacker;
    int64_t start_lead_ns;
    char wait_ready[MAX_WAIT][32];
    int n_wait;
    double ready_timeout_s;
    /* from the scenario (with the run options over it) */
    char scenario[64];
    double x0[PLANT_N];
    double deadline;             /* [run] deadline, a fraction of T */
    double u_max;                /* [controller] u_max */
    lienard plant;
} join_cfg;

/* Read and check the join file at path; 0, or -1 with a one-line reason in err. */
int join_read(const char *path, join_cfg *cfg, char *err, size_t errlen);

#endif
