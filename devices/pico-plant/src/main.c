/* tb-pico-plant: the paper's Lienard plant as a device on zenoh-pico, joining a testbed run through
 * its join file (TESTBED_JOIN), as docs/protocol.md specifies a plant node: it is the run's time
 * master (Start), samples x_k at t_k = k T on the run clock (Sensor), holds sample k until u_k or
 * the deadline t_k + d T, integrates x_{k+1} = phi_T(x_k, u_k) with its own RK4, publishes one
 * PlantTelemetry per sample and the final record, then Stop and its NodeSummary, and exits 0.
 *
 * Exit status: 0 the run ended (by the plant, or a Stop of the launcher); 1 a session or runtime
 * failure; 2 a bad or unsupported join file (one line on stderr); 3 the others were not ready in
 * time. */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include <mbedtls/sha256.h>
#include <zenoh-pico.h>

#include "join.h"
#include "json.h"
#include "plant.h"
#include "wire.h"

#define NAME "tb-pico-plant"
#define MAX_NAMES 16
#define MAX_TIMINGS (1 << 20)
#define ACT_RING 64

static join_cfg cfg;

/* ---- the run clock */
static int64_t mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static int64_t real_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* CLOCK_REALTIME - CLOCK_MONOTONIC, best of 7 reads (as testbed/nodes/clock.py) */
static int64_t realtime_minus_monotonic(void) {
    int64_t best_span = INT64_MAX, best = 0;
    for (int i = 0; i < 7; i++) {
        int64_t a = mono_ns(), r = real_ns(), b = mono_ns();
        if (b - a < best_span) {
            best_span = b - a;
            best = r - (a + (b - a) / 2);
        }
    }
    return best;
}

static volatile int clock_set = 0;
static int64_t t0_mono_ns;

static int64_t now_ns(void) { return mono_ns() - t0_mono_ns; }

static void sleep_mono_until(int64_t target_mono) {
    struct timespec ts = {(time_t)(target_mono / 1000000000LL), (long)(target_mono % 1000000000LL)};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {
    }
}

/* ---- shared state (the zenoh-pico read task calls the handlers) */
static pthread_mutex_t lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t cond;
static volatile sig_atomic_t signalled = 0;
static int stop_req = 0;
static char stop_reason[128];

typedef struct {
    char name[32];
    int alive, ready, seen_alive;
} peer;
static peer peers[MAX_NAMES];
static int n_peers;

typedef struct {
    int used;
    uint32_t k;
    uint8_t theta;
    double u[PLANT_M];
    int64_t rx_mono;
} act;
static act acts[ACT_RING];
static uint32_t waiting_k = 0;
static int controller_dead = 0, started = 0;
static long late_u = 0, future_u = 0, malformed = 0, misses = 0, no_u = 0, overruns = 0;
static long rejected = 0, clamped = 0, controller_lost_at = -1;
static uint32_t k_done = 0;

static z_owned_session_t session;
static z_owned_publisher_t pub_sensor, pub_start, pub_stop, pub_tel, pub_events, pub_summary;

static void die(int code, const char *fmt, ...) {
    va_list ap;
    fprintf(stderr, NAME ": ");
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
    exit(code);
}

static int key_of(char *out, size_t cap, const char *suffix) {
    int n = snprintf(out, cap, "%s/%s", cfg.prefix, suffix);
    return n > 0 && (size_t)n < cap ? 0 : -1;
}

/* ---- events (docs/protocol.md: Event; at most 20 per second per kind) */
typedef struct {
    char kind[32];
    int64_t window;
    int count;
} rate;
static rate rates[16];

static void event(const char *kind, long k, const char *fmt, ...) {
    char detail[200], buf[512];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(detail, sizeof detail, fmt, ap);
    va_end(ap);
    int64_t t = clock_set ? now_ns() : NO_TIME;
    int64_t w = mono_ns() / 1000000000LL;
    pthread_mutex_lock(&lock);
    int i, allowed = 1;
    for (i = 0; i < 16 && rates[i].kind[0]; i++)
        if (strcmp(rates[i].kind, kind) == 0) break;
    if (i < 16) {
        if (!rates[i].kind[0]) snprintf(rates[i].kind, sizeof rates[i].kind, "%s", kind);
        if (rates[i].window != w) {
            rates[i].window = w;
            rates[i].count = 0;
        }
        allowed = ++rates[i].count <= 20;
    }
    pthread_mutex_unlock(&lock);
    fprintf(stderr, NAME ": event %s k=%ld: %s\n", kind, k, detail);
    if (!allowed) return;
    size_t n = (size_t)snprintf(buf, sizeof buf, "{\"node\":\"plant\",\"kind\":\"%s\",\"k\":%ld,\"t_ns\":%lld,\"detail\":",
                                kind, k, (long long)t);
    n = json_str(buf, n, sizeof buf - 2, detail);
    if (n == 0) return;
    buf[n++] = '}';
    z_owned_bytes_t payload;
    z_bytes_copy_from_buf(&payload, (const uint8_t *)buf, n);
    z_publisher_put(z_publisher_loan(&pub_events), z_bytes_move(&payload), NULL);
}

/* ---- reading bytes of a sample, bounded */
static int read_bytes(const z_loaned_bytes_t *b, uint8_t *out, size_t want) {
    if (b == NULL || z_bytes_len(b) != want) return -1;
    z_bytes_reader_t r = z_bytes_get_reader(b);
    return z_bytes_reader_read(&r, out, want) == want ? 0 : -1;
}

/* ---- handlers */
static void on_actuation(z_loaned_sample_t *sample, void *arg) {
    (void)arg;
    int64_t rx = mono_ns();
    uint8_t h[HEADER_SIZE], p[5 + 8 * PLANT_M];
    const z_loaned_bytes_t *att = z_sample_attachment(sample);
    if (read_bytes(att, h, HEADER_SIZE) != 0) {
        pthread_mutex_lock(&lock);
        malformed++;
        pthread_mutex_unlock(&lock);
        event("malformed", -1, "actuation: header of %zu bytes, not 12", att ? z_bytes_len(att) : (size_t)0);
        return;
    }
    uint32_t k = get_u32(h);
    if (k == WARMUP_K) return;
    const z_loaned_bytes_t *pl = z_sample_payload(sample);
    if (read_bytes(pl, p, sizeof p) != 0 || p[0] > 1) {
        pthread_mutex_lock(&lock);
        malformed++;
        pthread_mutex_unlock(&lock);
        event("malformed", (long)k, "actuation: payload of %zu bytes (want %d) or theta not 0 or 1", z_bytes_len(pl),
              (int)sizeof p);
        return;
    }
    if (clock_set && (int64_t)k * cfg.T_ns > rx - t0_mono_ns + CLOCK_TOLERANCE_NS) {
        pthread_mutex_lock(&lock);
        future_u++;
        pthread_mutex_unlock(&lock);
        event("future_actuation", (long)k, "u for sample %lu before its instant: rejected", (unsigned long)k);
        return;
    }
    pthread_mutex_lock(&lock);
    act *a = &acts[k % ACT_RING];
    if (k < waiting_k || k >= cfg.n_steps || (a->used && a->k == k) || k - waiting_k >= ACT_RING) {
        late_u++;
    } else {
        a->used = 1;
        a->k = k;
        a->theta = p[0];
        for (int i = 0; i < PLANT_M; i++) a->u[i] = get_f64(p + 5 + 8 * i);
        a->rx_mono = rx;
        if (k == waiting_k) pthread_cond_broadcast(&cond);
    }
    pthread_mutex_unlock(&lock);
}

static jreader stop_reader;
static char stop_arena[4096];

static void on_stop(z_loaned_sample_t *sample, void *arg) {
    (void)arg;
    char text[4096];
    const z_loaned_bytes_t *pl = z_sample_payload(sample);
    size_t n = z_bytes_len(pl);
    if (n == 0 || n >= sizeof text || read_bytes(pl, (uint8_t *)text, n) != 0) return;
    pthread_mutex_lock(&lock);
    int root = jr_parse(&stop_reader, text, n, stop_arena, sizeof stop_arena);
    int o = jr_get(&stop_reader, root, "origin");
    int r = jr_get(&stop_reader, root, "reason");
    if (o >= 0 && stop_reader.nodes[o].type == J_STR && strcmp(stop_reader.nodes[o].str, "launcher") == 0 && !stop_req) {
        stop_req = 1;
        snprintf(stop_reason, sizeof stop_reason, "%s",
                 r >= 0 && stop_reader.nodes[r].type == J_STR ? stop_reader.nodes[r].str : "stopped by the launcher");
        pthread_cond_broadcast(&cond);
    }
    pthread_mutex_unlock(&lock);
}

static peer *peer_named(const char *name) {
    for (int i = 0; i < n_peers; i++)
        if (strcmp(peers[i].name, name) == 0) return &peers[i];
    if (n_peers >= MAX_NAMES || strlen(name) >= sizeof peers[0].name) return NULL;
    peer *p = &peers[n_peers++];
    memset(p, 0, sizeof *p);
    snprintf(p->name, sizeof p->name, "%s", name);
    return p;
}

static void on_liveliness(z_loaned_sample_t *sample, void *arg) {
    (void)arg;
    z_view_string_t ks;
    char key[256];
    z_keyexpr_as_view_string(z_sample_keyexpr(sample), &ks);
    size_t n = z_string_len(z_view_string_loan(&ks));
    if (n >= sizeof key) return;
    memcpy(key, z_string_data(z_view_string_loan(&ks)), n);
    key[n] = 0;
    size_t pl = strlen(cfg.prefix);
    if (strncmp(key, cfg.prefix, pl) != 0 || key[pl] != '/') return;
    const char *rest = key + pl + 1;
    int is_alive = strncmp(rest, "alive/", 6) == 0, is_ready = strncmp(rest, "ready/", 6) == 0;
    if (!is_alive && !is_ready) return;
    int put = z_sample_kind(sample) == Z_SAMPLE_KIND_PUT;
    int lost_controller = 0, lost_collector = 0;
    pthread_mutex_lock(&lock);
    peer *p = peer_named(rest + 6);
    if (p != NULL) {
        if (is_alive) {
            if (!put && p->alive && started && strcmp(p->name, "controller") == 0 && !controller_dead) {
                controller_dead = 1;
                controller_lost_at = (long)k_done;
                lost_controller = 1;
            }
            if (!put && p->seen_alive && strcmp(p->name, "collector") == 0 && !stop_req) {
                stop_req = 1;
                snprintf(stop_reason, sizeof stop_reason, "the launcher is gone");
                lost_collector = 1;
            }
            p->alive = put;
            p->seen_alive |= put;
        } else {
            p->ready = put;
        }
    }
    pthread_cond_broadcast(&cond);
    long at = controller_lost_at;
    pthread_mutex_unlock(&lock);
    if (lost_controller) event("controller_lost", at, "controller liveliness lost: running on with u = 0");
    if (lost_collector) event("peer_lost", -1, "the launcher's liveliness is gone: the run ends");
}

static void on_signal(int sig) {
    (void)sig;
    signalled = 1;
}

/* wait until every name is present (alive or ready), the plant itself counting as present */
static int wait_names(const char *const *names, int n, int ready, double timeout_s) {
    int64_t until = mono_ns() + (int64_t)(timeout_s * 1e9);
    pthread_mutex_lock(&lock);
    while (1) {
        int all = 1;
        for (int i = 0; i < n && all; i++) {
            if (strcmp(names[i], "plant") == 0) continue;
            peer *p = peer_named(names[i]);
            all = p != NULL && (ready ? p->ready : p->alive);
        }
        if (all || stop_req || signalled) {
            pthread_mutex_unlock(&lock);
            return all;
        }
        if (mono_ns() >= until) break;
        int64_t w = mono_ns() + 50000000LL;
        struct timespec ts = {(time_t)(w / 1000000000LL), (long)(w % 1000000000LL)};
        pthread_cond_timedwait(&cond, &lock, &ts);
    }
    pthread_mutex_unlock(&lock);
    return 0;
}

static void declare_pub(z_owned_publisher_t *pub, const char *suffix, int control) {
    char k[256];
    z_view_keyexpr_t ke;
    z_publisher_options_t o;
    if (key_of(k, sizeof k, suffix) || z_view_keyexpr_from_str(&ke, k) < 0) die(1, "bad key %s", k);
    z_publisher_options_default(&o);
    o.congestion_control = Z_CONGESTION_CONTROL_BLOCK;
    o.priority = control ? Z_PRIORITY_REAL_TIME : Z_PRIORITY_DATA_LOW;
    o.is_express = control != 0;
    if (z_declare_publisher(z_session_loan(&session), pub, z_view_keyexpr_loan(&ke), &o) < 0)
        die(1, "cannot declare a publisher on %s", k);
}

static void declare_sub(z_owned_subscriber_t *sub, const char *suffix, z_closure_sample_callback_t cb, int liveliness) {
    char k[256];
    z_view_keyexpr_t ke;
    z_owned_closure_sample_t closure;
    if (key_of(k, sizeof k, suffix) || z_view_keyexpr_from_str(&ke, k) < 0) die(1, "bad key %s", k);
    z_closure_sample(&closure, cb, NULL, NULL);
    int rc;
    if (liveliness) {
        z_liveliness_subscriber_options_t o;
        z_liveliness_subscriber_options_default(&o);
        o.history = true;
        rc = z_liveliness_declare_subscriber(z_session_loan(&session), sub, z_view_keyexpr_loan(&ke),
                                             z_closure_sample_move(&closure), &o);
    } else {
        rc = z_declare_subscriber(z_session_loan(&session), sub, z_view_keyexpr_loan(&ke),
                                  z_closure_sample_move(&closure), NULL);
    }
    if (rc < 0) die(1, "cannot subscribe to %s", k);
}

static void token(z_owned_liveliness_token_t *tok, const char *suffix) {
    char k[256];
    z_view_keyexpr_t ke;
    if (key_of(k, sizeof k, suffix) || z_view_keyexpr_from_str(&ke, k) < 0) die(1, "bad key %s", k);
    if (z_liveliness_declare_token(z_session_loan(&session), tok, z_view_keyexpr_loan(&ke), NULL) < 0)
        die(1, "cannot declare the liveliness token %s", k);
}

static void put(z_owned_publisher_t *pub, const uint8_t *data, size_t n, const uint8_t *att) {
    z_owned_bytes_t payload, attachment;
    z_publisher_put_options_t o;
    z_publisher_put_options_default(&o);
    z_bytes_copy_from_buf(&payload, data, n);
    if (att != NULL) {
        z_bytes_copy_from_buf(&attachment, att, HEADER_SIZE);
        o.attachment = z_bytes_move(&attachment);
    }
    z_publisher_put(z_publisher_loan(pub), z_bytes_move(&payload), &o);
}

/* docs/protocol.md (Telemetry): ask the launcher's collector on collector/summaries, after the summary, until its
 * reply (a JSON list of role names) holds "plant", at most 2 s and only while the collector's liveliness token is
 * there: a session closed right after its last put can lose it. 1: confirmed, 0: not in time, -1: no collector */
static int summary_received(void) {
    char k[256], buf[1024];
    z_view_keyexpr_t ke;
    if (key_of(k, sizeof k, "collector/summaries") || z_view_keyexpr_from_str(&ke, k) < 0) return 0;
    int64_t until = mono_ns() + 2000000000LL;
    while (mono_ns() < until) {
        pthread_mutex_lock(&lock);
        peer *c = peer_named("collector");
        int there = c != NULL && c->alive;
        pthread_mutex_unlock(&lock);
        if (!there) return -1;
        z_owned_closure_reply_t closure;
        z_owned_fifo_handler_reply_t handler;
        z_get_options_t o;
        int held = 0;
        z_fifo_channel_reply_new(&closure, &handler, 4);
        z_get_options_default(&o);
        o.timeout_ms = (uint64_t)((until - mono_ns()) / 1000000) + 1;
        if (z_get(z_session_loan(&session), z_view_keyexpr_loan(&ke), "", z_closure_reply_move(&closure), &o) == Z_OK) {
            z_owned_reply_t reply;
            while (z_fifo_handler_reply_recv(z_fifo_handler_reply_loan(&handler), &reply) == Z_OK) {
                z_owned_string_t str;
                if (z_reply_is_ok(z_reply_loan(&reply)) &&
                    z_bytes_to_string(z_sample_payload(z_reply_ok(z_reply_loan(&reply))), &str) == Z_OK) {
                    size_t n = z_string_len(z_string_loan(&str));
                    if (n < sizeof buf) { /* a longer reply is no list of the run's roles */
                        memcpy(buf, z_string_data(z_string_loan(&str)), n);
                        buf[n] = 0;
                        held |= strstr(buf, "\"plant\"") != NULL;
                    }
                    z_string_drop(z_string_move(&str));
                }
                z_reply_drop(z_reply_move(&reply));
            }
        }
        z_fifo_handler_reply_drop(z_fifo_handler_reply_move(&handler));
        if (held) return 1;
        sleep_mono_until(mono_ns() + 20000000LL);
    }
    return 0;
}

/* ---- timing statistics (percentiles as numpy's default, linear) */
typedef struct {
    int64_t *v;
    size_t n, cap;
    int64_t max;
    size_t total;
} timings;

static void tm_add(timings *t, int64_t x) {
    if (t->total == 0 || x > t->max) t->max = x;
    t->total++;
    if (t->n < t->cap) t->v[t->n++] = x;
}

static int cmp64(const void *a, const void *b) {
    int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

static double pct(const int64_t *s, size_t n, double q) {
    double pos = q / 100.0 * (double)(n - 1);
    size_t lo = (size_t)floor(pos), hi = lo + 1 < n ? lo + 1 : lo;
    return (double)s[lo] + (pos - (double)lo) * (double)(s[hi] - s[lo]);
}

static size_t tm_json(char *out, size_t cap, timings *t) {
    if (t->n == 0) return (size_t)snprintf(out, cap, "{\"p50\":null,\"p99\":null,\"max\":null,\"n\":0}");
    qsort(t->v, t->n, sizeof t->v[0], cmp64);
    return (size_t)snprintf(out, cap, "{\"p50\":%.17g,\"p99\":%.17g,\"max\":%.17g,\"n\":%zu}", pct(t->v, t->n, 50) / 1e3,
                            pct(t->v, t->n, 99) / 1e3, (double)t->max / 1e3, t->total);
}

int main(void) {
    char err[300];
    const char *path = getenv("TESTBED_JOIN");
    if (path == NULL || !path[0]) die(2, "no TESTBED_JOIN: the join file of a run (testbed run SCENARIO --external plant)");
    if (join_read(path, &cfg, err, sizeof err) != 0) die(2, "join file %s: %s", path, err);
    pthread_condattr_t ca;
    pthread_condattr_init(&ca);
    pthread_condattr_setclock(&ca, CLOCK_MONOTONIC);
    pthread_cond_init(&cond, &ca);
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);

    /* ---- session: a Zenoh client of the run's router; mutual TLS with the role's certificate */
    z_owned_config_t zc;
    z_config_default(&zc);
    int bad = zp_config_insert(z_config_loan_mut(&zc), Z_CONFIG_MODE_KEY, "client") != Z_OK;
    for (int i = 0; i < cfg.n_connect; i++)
        bad |= zp_config_insert(z_config_loan_mut(&zc), Z_CONFIG_CONNECT_KEY, cfg.connect[i]) != Z_OK;
    if (cfg.mutual_tls) {
        bad |= zp_config_insert(z_config_loan_mut(&zc), Z_CONFIG_TLS_ROOT_CA_CERTIFICATE_KEY, cfg.ca) != Z_OK;
        bad |= zp_config_insert(z_config_loan_mut(&zc), Z_CONFIG_TLS_ENABLE_MTLS_KEY, "true") != Z_OK;
        bad |= zp_config_insert(z_config_loan_mut(&zc), Z_CONFIG_TLS_CONNECT_PRIVATE_KEY_KEY, cfg.key) != Z_OK;
        bad |= zp_config_insert(z_config_loan_mut(&zc), Z_CONFIG_TLS_CONNECT_CERTIFICATE_KEY, cfg.cert) != Z_OK;
        bad |= zp_config_insert(z_config_loan_mut(&zc), Z_CONFIG_TLS_VERIFY_NAME_ON_CONNECT_KEY, "false") != Z_OK;
    }
    if (bad) die(2, "join file %s: the session's configuration was refused", path);
    /* the router may not listen yet when the join file appears: try again after 10 ms, doubling up to
     * 1 s, within the run's startup timeout (z_open consumes the configuration: clone it per try) */
    int64_t give_up = mono_ns() + (int64_t)(cfg.ready_timeout_s * 1e9);
    int64_t pause = 10000000LL;
    while (1) {
        z_owned_config_t try_cfg;
        if (z_config_clone(&try_cfg, z_config_loan(&zc)) < 0) die(1, "out of memory");
        if (z_open(&session, z_config_move(&try_cfg), NULL) >= 0) break;
        if (signalled) die(1, "interrupted before its session to %s opened", cfg.connect[0]);
        if (mono_ns() + pause > give_up)
            die(1, "cannot open a Zenoh session to %s (%s)", cfg.connect[0], cfg.mutual_tls ? "mutual TLS" : "TCP");
        sleep_mono_until(mono_ns() + pause);
        pause = pause * 2 > 1000000000LL ? 1000000000LL : pause * 2;
    }
    z_config_drop(z_config_move(&zc));

    z_owned_subscriber_t sub_act, sub_stop, sub_alive, sub_ready;
    declare_pub(&pub_sensor, "loop/sensor", 1); /* the publishers first: a handler may publish an event */
    declare_pub(&pub_start, "control/start", 1);
    declare_pub(&pub_stop, "control/stop", 1);
    declare_pub(&pub_tel, "telemetry/plant", 0);
    declare_pub(&pub_events, "events/plant", 0);
    declare_pub(&pub_summary, "summary/plant", 0);
    declare_sub(&sub_act, "loop/actuation", on_actuation, 0);
    declare_sub(&sub_stop, "control/stop", on_stop, 0);
    declare_sub(&sub_alive, "alive/*", on_liveliness, 1);
    declare_sub(&sub_ready, "ready/*", on_liveliness, 1);

    /* ---- start-up (docs/protocol.md: liveliness, readiness and the Start handshake) */
    z_owned_liveliness_token_t tok_alive, tok_ready;
    token(&tok_alive, "alive/plant");
    static const char *const roles[] = {"plant", "encoder", "attacker", "controller"};
    if (!wait_names(roles, 4, 0, cfg.ready_timeout_s)) {
        if (!signalled && !stop_req) die(3, "the other roles were not alive after %g s", cfg.ready_timeout_s);
    }
    uint8_t hdr[HEADER_SIZE], xbuf[8 * PLANT_N];
    for (int i = 0; i < PLANT_N; i++) put_f64(xbuf + 8 * i, cfg.x0[i]);
    for (int i = 0; i < 3; i++) { /* warm-up puts: every reader ignores k = WARMUP_K */
        header_encode(hdr, WARMUP_K, 0);
        put(&pub_sensor, xbuf, sizeof xbuf, hdr);
    }
    token(&tok_ready, "ready/plant");
    const char *wait[MAX_WAIT];
    for (int i = 0; i < cfg.n_wait; i++) wait[i] = cfg.wait_ready[i];
    if (!wait_names(wait, cfg.n_wait, 1, cfg.ready_timeout_s) && !signalled && !stop_req)
        die(3, "the run was not ready after %g s", cfg.ready_timeout_s);
    pthread_mutex_lock(&lock);
    int early = stop_req || signalled;
    pthread_mutex_unlock(&lock);
    if (early) { /* stopped before the run started: no Start, nothing of the run was due */
        fprintf(stderr, NAME ": stopped before the run started (%s)\n", signalled ? "signal" : stop_reason);
        z_liveliness_token_drop(z_liveliness_token_move(&tok_ready));
        z_liveliness_token_drop(z_liveliness_token_move(&tok_alive));
        z_session_drop(z_session_move(&session));
        return 0;
    }

    const int64_t T_ns = cfg.T_ns, N = cfg.n_steps;
    const double T = (double)T_ns / 1e9;
    const int64_t d_ns = (int64_t)(cfg.deadline * (double)T_ns);
    const int64_t spin_ns = T_ns / 20 < 200000 ? T_ns / 20 : 200000;
    int64_t t0 = real_ns() + cfg.start_lead_ns;
    t0_mono_ns = t0 - realtime_minus_monotonic();
    clock_set = 1;
    char start[512];
    size_t sl = (size_t)snprintf(start, sizeof start, "{\"run_id\":");
    sl = json_str(start, sl, sizeof start, cfg.run_id);
    sl += (size_t)snprintf(start + sl, sizeof start - sl,
                           ",\"t0_ns\":%lld,\"T_ns\":%lld,\"n_steps\":%lld,\"digest\":\"%s\",\"timing\":\"ideal\","
                           "\"ack_via_attacker\":%s,\"protocol\":%d}",
                           (long long)t0, (long long)T_ns, (long long)N, cfg.digest,
                           cfg.ack_via_attacker ? "true" : "false", PROTOCOL_VERSION);
    put(&pub_start, (const uint8_t *)start, sl, NULL);
    pthread_mutex_lock(&lock);
    started = 1;
    pthread_mutex_unlock(&lock);
    while (!signalled && now_ns() < -20000000LL) { /* again every 50 ms until 20 ms before t0 */
        int64_t next = mono_ns() + 50000000LL, last = t0_mono_ns - 20000000LL;
        sleep_mono_until(next < last ? next : last);
        if (now_ns() < -20000000LL) put(&pub_start, (const uint8_t *)start, sl, NULL);
    }

    /* ---- the loop */
    lienard plant = cfg.plant;
    double x[PLANT_N];
    memcpy(x, cfg.x0, sizeof x);
    mbedtls_sha256_context sha;
    mbedtls_sha256_init(&sha);
    mbedtls_sha256_starts(&sha, 0);
    long records = 0;
    int flow_status = FLOW_OK;
    long diverged_at = -1;
    size_t cap = N < MAX_TIMINGS ? (size_t)N : MAX_TIMINGS;
    timings jitter = {calloc(cap, 8), 0, cap, 0, 0}, latency = {calloc(cap, 8), 0, cap, 0, 0};
    if (!jitter.v || !latency.v) die(1, "out of memory");
    uint8_t rec[2 + 256];
    for (int64_t k = 0; k < N; k++) {
        if (signalled || stop_req) break;
        int64_t due = t0_mono_ns + k * T_ns;
        if (due - mono_ns() > spin_ns) sleep_mono_until(due - spin_ns);
        while (mono_ns() < due) { /* spin the last part: the sample instant to the microsecond */
        }
        int64_t t_act = now_ns();
        if (signalled || stop_req) break;
        pthread_mutex_lock(&lock);
        waiting_k = (uint32_t)k;
        pthread_mutex_unlock(&lock);
        uint8_t xs[8 * PLANT_N];
        for (int i = 0; i < PLANT_N; i++) put_f64(xs + 8 * i, x[i]);
        header_encode(hdr, (uint32_t)k, t_act);
        put(&pub_sensor, xs, sizeof xs, hdr);
        int64_t sensor_tx = now_ns();
        /* hold t_k until u_k or the (nominal) deadline t_k + d T */
        int64_t deadline_mono = t0_mono_ns + k * T_ns + d_ns;
        struct timespec dl = {(time_t)(deadline_mono / 1000000000LL), (long)(deadline_mono % 1000000000LL)};
        act a;
        memset(&a, 0, sizeof a);
        int have = 0, dead;
        pthread_mutex_lock(&lock);
        while (1) {
            act *s = &acts[k % ACT_RING];
            if (s->used && s->k == (uint32_t)k) {
                a = *s;
                s->used = 0;
                have = 1;
                break;
            }
            if (controller_dead || stop_req || signalled || mono_ns() >= deadline_mono) break;
            pthread_cond_timedwait(&cond, &lock, &dl);
        }
        waiting_k = (uint32_t)k + 1;
        dead = controller_dead;
        pthread_mutex_unlock(&lock);
        uint8_t flags = 0, theta;
        double u[PLANT_M] = {0.0};
        int64_t u_rx = NO_TIME;
        int use = 0;
        if (have) {
            int finite = 1, over = 0;
            for (int i = 0; i < PLANT_M; i++) {
                finite &= isfinite(a.u[i]) != 0;
                over |= fabs(a.u[i]) > cfg.u_max;
            }
            if (!finite) {
                rejected++;
                event("input_rejected", (long)k, "u_k has a non-finite entry: u_k = 0 applied");
            } else {
                use = 1;
                for (int i = 0; i < PLANT_M; i++)
                    u[i] = a.u[i] > cfg.u_max ? cfg.u_max : a.u[i] < -cfg.u_max ? -cfg.u_max : a.u[i];
                if (over) {
                    clamped++;
                    event("input_clamped", (long)k, "|u_k| above u_max = %g: clamped", cfg.u_max);
                }
            }
        }
        if (use) {
            theta = a.theta;
            u_rx = a.rx_mono - t0_mono_ns;
            tm_add(&latency, u_rx - t_act);
        } else {
            theta = have ? a.theta : THETA_NONE;
            flags |= FLAG_NO_U;
            no_u++;
            if (dead) {
                flags |= FLAG_CTRL_DEAD;
            } else if (!have) {
                flags |= FLAG_MISS;
                misses++;
            }
        }
        int64_t jit = t_act - k * T_ns;
        tm_add(&jitter, jit);
        if (jit > d_ns) overruns++;
        double xk[PLANT_N];
        memcpy(xk, x, sizeof x);
        int st = lienard_flow(&plant, x, u, T);
        size_t n = plant_telemetry(rec + 2, sizeof rec - 2, (uint32_t)k, t_act, sensor_tx, u_rx, 0, theta, flags,
                                   (int8_t)st, xk, PLANT_N, u, PLANT_M);
        rec[0] = (uint8_t)(n & 0xFF);
        rec[1] = (uint8_t)(n >> 8);
        mbedtls_sha256_update(&sha, rec + 2, n);
        records++;
        put(&pub_tel, rec, n + 2, NULL);
        pthread_mutex_lock(&lock);
        k_done = (uint32_t)k + 1;
        pthread_mutex_unlock(&lock);
        if (st != FLOW_OK) {
            flow_status = st;
            diverged_at = (long)k;
            event("flow_diverged", (long)k, "phi_T status diverged: run ends");
            break;
        }
    }

    /* ---- the end: final record, Stop, summary */
    size_t n = plant_telemetry(rec + 2, sizeof rec - 2, k_done, now_ns(), NO_TIME, NO_TIME, 0, THETA_NONE, FLAG_FINAL,
                               (int8_t)flow_status, x, PLANT_N, NULL, 0);
    rec[0] = (uint8_t)(n & 0xFF);
    rec[1] = (uint8_t)(n >> 8);
    mbedtls_sha256_update(&sha, rec + 2, n);
    records++;
    put(&pub_tel, rec, n + 2, NULL);
    char reason[160], stop[400];
    if ((int64_t)k_done == N) snprintf(reason, sizeof reason, "done");
    else if (diverged_at >= 0) snprintf(reason, sizeof reason, "flow diverged at sample %ld", diverged_at);
    else if (signalled) snprintf(reason, sizeof reason, "interrupted (signal)");
    else snprintf(reason, sizeof reason, "%s", stop_reason[0] ? stop_reason : "stopped");
    size_t s = (size_t)snprintf(stop, sizeof stop, "{\"reason\":");
    s = json_str(stop, s, sizeof stop - 40, reason);
    s += (size_t)snprintf(stop + s, sizeof stop - s, ",\"origin\":\"plant\"}");
    put(&pub_stop, (const uint8_t *)stop, s, NULL);

    unsigned char digest[32];
    char hex[65];
    mbedtls_sha256_finish(&sha, digest);
    mbedtls_sha256_free(&sha);
    for (int i = 0; i < 32; i++) snprintf(hex + 2 * i, 3, "%02x", digest[i]);
    char jit_s[160], lat_s[160], summary[1400], ns[96] = "null";
#ifdef __linux__
    { /* the network namespace the device ran in, as the bundled nodes report it */
        char link[64];
        ssize_t len = readlink("/proc/self/ns/net", link, sizeof link - 1);
        if (len > 0 && len < (ssize_t)sizeof link - 1) {
            link[len] = 0;
            json_str(ns, 0, sizeof ns, link);
        }
    }
#endif
    tm_json(jit_s, sizeof jit_s, &jitter);
    tm_json(lat_s, sizeof lat_s, &latency);
    pthread_mutex_lock(&lock);
    size_t m = (size_t)snprintf(
        summary, sizeof summary,
        "{\"node\":\"plant\",\"data\":{\"samples\":%lu,\"deadline_misses\":%ld,\"u_missing\":%ld,\"late_u\":%ld,"
        "\"future_u\":%ld,\"inputs_rejected\":%ld,\"inputs_clamped\":%ld,\"overruns\":%ld,\"malformed\":%ld,"
        "\"controller_lost_at\":%ld,\"timing\":\"ideal\",\"plant_fault\":null,\"plant_fault_at\":-1,"
        "\"jitter_us\":%s,\"latency_us\":%s,\"spin_us\":%.17g,\"colocated\":[],\"netns\":%s,"
        "\"implementation\":\"tb-pico-plant (C99, zenoh-pico)\",\"integrator\":\"rk4\",\"rk4_substeps\":%ld,"
        "\"telemetry_records\":%ld,\"telemetry_sha256\":\"%s\"}}",
        (unsigned long)k_done, misses, no_u, late_u, future_u, rejected, clamped, overruns, malformed,
        controller_lost_at, jit_s, lat_s, (double)spin_ns / 1e3, ns, rk4_substeps(T), records, hex);
    pthread_mutex_unlock(&lock);
    if (m < sizeof summary) {
        put(&pub_summary, (const uint8_t *)summary, m, NULL);
        if (summary_received() == 0) fprintf(stderr, NAME ": the collector did not confirm the summary in 2 s\n");
    }
    free(jitter.v);
    free(latency.v);

    z_liveliness_token_drop(z_liveliness_token_move(&tok_ready));
    z_liveliness_token_drop(z_liveliness_token_move(&tok_alive));
    z_subscriber_drop(z_subscriber_move(&sub_act));
    z_subscriber_drop(z_subscriber_move(&sub_stop));
    z_subscriber_drop(z_subscriber_move(&sub_alive));
    z_subscriber_drop(z_subscriber_move(&sub_ready));
    z_publisher_drop(z_publisher_move(&pub_sensor));
    z_publisher_drop(z_publisher_move(&pub_start));
    z_publisher_drop(z_publisher_move(&pub_stop));
    z_publisher_drop(z_publisher_move(&pub_tel));
    z_publisher_drop(z_publisher_move(&pub_events));
    z_publisher_drop(z_publisher_move(&pub_summary));
    z_session_drop(z_session_move(&session));
    return 0;
}
