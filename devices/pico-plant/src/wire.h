/* Byte layouts of docs/protocol.md (little-endian) and JSON text for the bookkeeping messages. */
#ifndef PICO_PLANT_WIRE_H
#define PICO_PLANT_WIRE_H

#include <stddef.h>
#include <stdint.h>

#define PROTOCOL_VERSION 1
#define HEADER_SIZE 12
#define WARMUP_K 0xFFFFFFFFu
#define NO_TIME INT64_MIN
#define THETA_NONE 255
#define CLOCK_TOLERANCE_NS 2000000LL

#define FLAG_MISS 1u
#define FLAG_NO_U 2u
#define FLAG_CTRL_DEAD 4u
#define FLAG_FINAL 8u

void put_u32(uint8_t *p, uint32_t v);
void put_i64(uint8_t *p, int64_t v);
void put_f64(uint8_t *p, double v);
uint32_t get_u32(const uint8_t *p);
int32_t get_i32(const uint8_t *p);
int64_t get_i64(const uint8_t *p);
double get_f64(const uint8_t *p);

void header_encode(uint8_t out[HEADER_SIZE], uint32_t k, int64_t stamp_ns);

/* one PlantTelemetry record (scalars <IqqqqBBb, then x and u as uint8 length + float64s); returns
 * its length, or 0 when cap is too small */
size_t plant_telemetry(uint8_t *out, size_t cap, uint32_t k, int64_t t_ns, int64_t sensor_tx_ns, int64_t u_rx_ns,
                       int64_t delay_ns, uint8_t theta, uint8_t flags, int8_t flow_status, const double *x, int n,
                       const double *u, int m);

/* append s to out as a JSON string (quoted, escaped); returns the new length or 0 if it does not fit */
size_t json_str(char *out, size_t len, size_t cap, const char *s);

#endif
