/* See wire.h. Portable byte order: no casts of buffers, shifts only. */
#include "wire.h"

#include <stdio.h>
#include <string.h>

void put_u32(uint8_t *p, uint32_t v) {
    for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}

void put_i64(uint8_t *p, int64_t v) {
    uint64_t u = (uint64_t)v;
    for (int i = 0; i < 8; i++) p[i] = (uint8_t)(u >> (8 * i));
}

void put_f64(uint8_t *p, double v) {
    uint64_t u;
    memcpy(&u, &v, 8);
    for (int i = 0; i < 8; i++) p[i] = (uint8_t)(u >> (8 * i));
}

uint32_t get_u32(const uint8_t *p) {
    uint32_t v = 0;
    for (int i = 3; i >= 0; i--) v = (v << 8) | p[i];
    return v;
}

int32_t get_i32(const uint8_t *p) {
    uint32_t u = get_u32(p);
    int32_t v;
    memcpy(&v, &u, 4);
    return v;
}

int64_t get_i64(const uint8_t *p) {
    uint64_t u = 0;
    for (int i = 7; i >= 0; i--) u = (u << 8) | p[i];
    int64_t v;
    memcpy(&v, &u, 8);
    return v;
}

double get_f64(const uint8_t *p) {
    uint64_t u = 0;
    for (int i = 7; i >= 0; i--) u = (u << 8) | p[i];
    double v;
    memcpy(&v, &u, 8);
    return v;
}

void header_encode(uint8_t out[HEADER_SIZE], uint32_t k, int64_t stamp_ns) {
    put_u32(out, k);
    put_i64(out + 4, stamp_ns);
}

size_t plant_telemetry(uint8_t *out, size_t cap, uint32_t k, int64_t t_ns, int64_t sensor_tx_ns, int64_t u_rx_ns,
                       int64_t delay_ns, uint8_t theta, uint8_t flags, int8_t flow_status, const double *x, int n,
                       const double *u, int m) {
    size_t need = 39 + 1 + 8 * (size_t)n + 1 + 8 * (size_t)m;
    if (need > cap || n > 255 || m > 255) return 0;
    put_u32(out, k);
    put_i64(out + 4, t_ns);
    put_i64(out + 12, sensor_tx_ns);
    put_i64(out + 20, u_rx_ns);
    put_i64(out + 28, delay_ns);
    out[36] = theta;
    out[37] = flags;
    out[38] = (uint8_t)flow_status;
    size_t o = 39;
    out[o++] = (uint8_t)n;
    for (int i = 0; i < n; i++, o += 8) put_f64(out + o, x[i]);
    out[o++] = (uint8_t)m;
    for (int i = 0; i < m; i++, o += 8) put_f64(out + o, u[i]);
    return o;
}

size_t json_str(char *out, size_t len, size_t cap, const char *s) {
    if (len + 2 >= cap) return 0;
    out[len++] = '"';
    for (; *s; s++) {
        unsigned char c = (unsigned char)*s;
        char esc[8];
        size_t el;
        if (c == '"' || c == '\\') {
            esc[0] = '\\';
            esc[1] = (char)c;
            el = 2;
        } else if (c < 0x20) {
            el = (size_t)snprintf(esc, sizeof esc, "\\u%04x", c);
        } else {
            esc[0] = (char)c;
            el = 1;
        }
        if (len + el + 2 >= cap) return 0;
        memcpy(out + len, esc, el);
        len += el;
    }
    out[len++] = '"';
    out[len] = 0;
    return len;
}
