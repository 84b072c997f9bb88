/* See join.h. The fields and their checks follow testbed/wire/join.py; what this device cannot do
 * (another role, the peer topology, a password, Zenoh's low-latency transport, physical timing, a
 * plant other than the Lienard system, a sensor/actuator model, a [network] channel) is refused with
 * one line, never run wrongly. */
#include "join.h"

#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "json.h"
#include "toml.h"

static const char *const FIELDS[] = {"join_version", "protocol",    "role",        "run_id",
                                     "key_prefix",   "ack_key",     "topology",    "mode",
                                     "connect",      "listen",      "low_latency", "credentials",
                                     "T_ns",         "n_steps",     "timing",      "ack_via_attacker",
                                     "digest",       "t0_ns",       "start_lead_ns", "wait_ready",
                                     "ready_timeout_s", "run_options", "scenario"};
#define N_FIELDS (sizeof FIELDS / sizeof FIELDS[0])

/* big buffers: static, so that a small stack is enough (as on a microcontroller) */
static char text[JOIN_MAX_BYTES + 1];
static char arena[JOIN_MAX_BYTES + 1];
static jreader jr;
static tvdoc toml;

typedef struct {
    char *err;
    size_t len;
} errbuf;

static int bad(errbuf *e, const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(e->err, e->len, fmt, ap);
    va_end(ap);
    return -1;
}

static int field(errbuf *e, int root, const char *name, enum jtype t, const char *what) {
    int i = jr_get(&jr, root, name);
    enum jtype got = i < 0 ? J_NULL : jr.nodes[i].type;
    if (t == J_TRUE && (got == J_TRUE || got == J_FALSE)) return i;
    if (i < 0 || got != t) return bad(e, "%s: expected %s", name, what);
    return i;
}

static int str_into(errbuf *e, int root, const char *name, char *out, size_t cap) {
    int i = field(e, root, name, J_STR, "a string");
    if (i < 0) return -1;
    if (jr.nodes[i].len + 1 > cap) return bad(e, "%s: longer than %zu bytes", name, cap - 1);
    memcpy(out, jr.nodes[i].str, jr.nodes[i].len + 1);
    return 0;
}

static int int_field(errbuf *e, int root, const char *name, long long lo, long long hi, long long *out) {
    int i = field(e, root, name, J_NUM, "an integer");
    if (i < 0) return -1;
    if (!jr.nodes[i].is_int) return bad(e, "%s: expected an integer", name);
    if (jr.nodes[i].ival < lo || jr.nodes[i].ival > hi) return bad(e, "%s: %lld is out of range", name, jr.nodes[i].ival);
    *out = jr.nodes[i].ival;
    return 0;
}

static int is_str(int i, const char *s) { return i >= 0 && jr.nodes[i].type == J_STR && strcmp(jr.nodes[i].str, s) == 0; }

/* a file the session will read: must exist as a regular file */
static int check_file(errbuf *e, const char *what, const char *path) {
    struct stat st;
    if (stat(path, &st) != 0) return bad(e, "credentials.%s %s: %s", what, path, strerror(errno));
    if (!S_ISREG(st.st_mode)) return bad(e, "credentials.%s %s: not a regular file", what, path);
    return 0;
}

static int scenario(errbuf *e, join_cfg *c, int sc, int opts) {
    if (sc < 0 || jr.nodes[sc].type != J_OBJ || jr.nodes[sc].count != 3 || jr_get(&jr, sc, "base_dir") < 0)
        return bad(e, "scenario: expected name, toml and base_dir");
    if (str_into(e, sc, "name", c->scenario, sizeof c->scenario)) return -1;
    int t = field(e, sc, "toml", J_STR, "a string");
    if (t < 0) return -1;
    if (tv_parse(&toml, jr.nodes[t].str, jr.nodes[t].len)) return bad(e, "%s", toml.err);
    for (int i = 0; i < toml.n_tables; i++) {
        const char *tb = toml.tables[i];
        if (strncmp(tb, "network", 7) == 0 && (tb[7] == 0 || tb[7] == '.'))
            return bad(e, "the scenario has a [network] channel: this device does not model one");
    }
    for (int i = 0; i < toml.n_tables; i++)
        if (strncmp(toml.tables[i], "plant.", 6) == 0)
            return bad(e, "[%s]: this device has no sensor, actuator or disturbance model", toml.tables[i]);
    for (int i = 0; i < toml.n; i++) {
        const char *p = toml.leaves[i].path;
        if (strncmp(p, "network", 7) == 0 && (p[7] == 0 || p[7] == '.'))
            return bad(e, "the scenario has a [network] channel: this device does not model one");
        if (strncmp(p, "plant.", 6) != 0) continue;
        p += 6;
        if (!strncmp(p, "sensor", 6) || !strncmp(p, "actuator", 8) || !strncmp(p, "disturbance", 11))
            return bad(e, "[plant] %s: this device has no sensor, actuator or disturbance model", p);
        if (strcmp(p, "name") && strcmp(p, "x0") && strcmp(p, "params.a") && strcmp(p, "params.b"))
            return bad(e, "[plant] %s: this device runs the Lienard plant with params a, b and x0 only", p);
    }
    const tvleaf *l = tv_find(&toml, "plant.name");
    if (!l || l->type != TV_STR || strcmp(l->str, "lienard") != 0)
        return bad(e, "[plant] name: this device runs the plant \"lienard\" only");
    c->plant.a = 1.0 / 3.0;
    c->plant.b = 1.0 / 50.0;
    if ((l = tv_find(&toml, "plant.params.a"))) {
        if (l->type != TV_NUM || !isfinite(l->num)) return bad(e, "[plant] params.a: expected a finite number");
        c->plant.a = l->num;
    }
    if ((l = tv_find(&toml, "plant.params.b"))) {
        if (l->type != TV_NUM || !isfinite(l->num)) return bad(e, "[plant] params.b: expected a finite number");
        c->plant.b = l->num;
    }
    l = tv_find(&toml, "plant.x0");
    if (!l || l->type != TV_NUMARR || l->arr_n != PLANT_N) return bad(e, "[plant] x0: expected %d numbers", PLANT_N);
    for (int i = 0; i < PLANT_N; i++) {
        if (!isfinite(l->arr[i])) return bad(e, "[plant] x0: not finite");
        c->x0[i] = l->arr[i];
    }
    c->deadline = 0.5;
    if ((l = tv_find(&toml, "run.deadline"))) {
        if (l->type != TV_NUM) return bad(e, "[run] deadline: expected a number");
        c->deadline = l->num;
    }
    int d = jr_get(&jr, opts, "deadline");
    if (d >= 0 && jr.nodes[d].type == J_NUM) c->deadline = jr.nodes[d].num;
    else if (d >= 0 && jr.nodes[d].type != J_NULL) return bad(e, "run_options.deadline: expected a number or null");
    if (!(c->deadline > 0.0 && c->deadline < 1.0)) return bad(e, "deadline %g: must be in (0, 1)", c->deadline);
    c->u_max = 1e6;
    if ((l = tv_find(&toml, "controller.u_max"))) {
        if (l->type != TV_NUM || !(l->num > 0.0)) return bad(e, "[controller] u_max: expected a positive number");
        c->u_max = l->num;
    }
    c->plant.x_max = 1e8;
    if ((l = tv_find(&toml, "flow.x_max"))) {
        if (l->type != TV_NUM || !(l->num > 0.0)) return bad(e, "[flow] x_max: expected a positive number");
        c->plant.x_max = l->num;
    }
    return 0;
}

int join_read(const char *path, join_cfg *c, char *err, size_t errlen) {
    errbuf e = {err, errlen};
    struct stat st;
    memset(c, 0, sizeof *c);
    if (stat(path, &st) != 0) return bad(&e, "%s", strerror(errno));
    if (!S_ISREG(st.st_mode)) return bad(&e, "not a regular file");
    if (st.st_mode & 077) return bad(&e, "readable by others (mode %o): it holds the run's credentials", st.st_mode & 0777);
    if (st.st_size > JOIN_MAX_BYTES) return bad(&e, "%lld bytes is not a join file", (long long)st.st_size);
    FILE *f = fopen(path, "rb");
    if (!f) return bad(&e, "%s", strerror(errno));
    size_t n = fread(text, 1, JOIN_MAX_BYTES + 1, f);
    int rerr = ferror(f);
    fclose(f);
    if (rerr) return bad(&e, "read error");
    if (n > JOIN_MAX_BYTES) return bad(&e, "more than %d bytes is not a join file", JOIN_MAX_BYTES);
    int root = jr_parse(&jr, text, n, arena, sizeof arena);
    if (root < 0) return bad(&e, "not a JSON join file: %s", jr.err);
    if (jr.nodes[root].type != J_OBJ) return bad(&e, "not a JSON object");
    for (size_t i = 0; i < N_FIELDS; i++)
        if (jr_get(&jr, root, FIELDS[i]) < 0) return bad(&e, "missing %s", FIELDS[i]);
    for (int ch = jr.nodes[root].first; ch >= 0; ch = jr.nodes[ch].next) {
        size_t i;
        for (i = 0; i < N_FIELDS; i++)
            if (strcmp(jr.nodes[ch].key, FIELDS[i]) == 0) break;
        if (i == N_FIELDS) return bad(&e, "unknown %.60s", jr.nodes[ch].key);
    }
    long long v;
    if (int_field(&e, root, "join_version", 0, 1000000, &v)) return -1;
    if (v != 1) return bad(&e, "join_version %lld: this node reads version 1", v);
    if (int_field(&e, root, "protocol", 0, 1000000, &v)) return -1;
    if (v != 1) return bad(&e, "the run speaks protocol version %lld, this node speaks 1", v);
    int i = field(&e, root, "role", J_STR, "a role");
    if (i < 0) return -1;
    if (!is_str(i, "plant")) return bad(&e, "role %.20s: this device is a plant", jr.nodes[i].str);
    if (str_into(&e, root, "run_id", c->run_id, sizeof c->run_id)) return -1;
    if (!c->run_id[0]) return bad(&e, "run_id: empty");
    for (const char *p = c->run_id; *p; p++)
        if (strchr("/*$?#\"\\", *p) || (unsigned char)*p < 0x20 || (unsigned char)*p >= 0x7f)
            return bad(&e, "run_id: not a plain key chunk");
    snprintf(c->prefix, sizeof c->prefix, "testbed/%s", c->run_id);
    i = field(&e, root, "key_prefix", J_STR, "a string");
    if (i < 0) return -1;
    if (!is_str(i, c->prefix)) return bad(&e, "key_prefix is not %s", c->prefix);
    if (field(&e, root, "ack_key", J_STR, "a string") < 0) return -1;
    i = field(&e, root, "topology", J_STR, "a string");
    if (i < 0) return -1;
    if (!is_str(i, "router"))
        return bad(&e, "topology %.20s: zenoh-pico joins the router topology only (testbed run --topology router)",
                   jr.nodes[i].str);
    i = field(&e, root, "mode", J_STR, "a string");
    if (i < 0) return -1;
    if (!is_str(i, "client")) return bad(&e, "mode %.20s: this device is a Zenoh client", jr.nodes[i].str);
    int a = field(&e, root, "connect", J_ARR, "a list of strings");
    if (a < 0) return -1;
    if (jr.nodes[a].count < 1 || jr.nodes[a].count > MAX_ENDPOINTS)
        return bad(&e, "connect: expected 1 to %d endpoints", MAX_ENDPOINTS);
    for (int k = 0; k < jr.nodes[a].count; k++) {
        int s = jr_at(&jr, a, k);
        if (jr.nodes[s].type != J_STR || jr.nodes[s].len >= sizeof c->connect[0] || jr.nodes[s].len == 0)
            return bad(&e, "connect: expected a list of endpoints");
        memcpy(c->connect[k], jr.nodes[s].str, jr.nodes[s].len + 1);
    }
    c->n_connect = jr.nodes[a].count;
    a = field(&e, root, "listen", J_ARR, "a list of strings");
    if (a < 0) return -1;
    if (jr.nodes[a].count != 0) return bad(&e, "listen: a client listens on nothing");
    i = field(&e, root, "low_latency", J_TRUE, "true or false");
    if (i < 0) return -1;
    if (jr.nodes[i].type == J_TRUE) return bad(&e, "low_latency: zenoh-pico has no low-latency transport");
    int cr = field(&e, root, "credentials", J_OBJ, "an object");
    if (cr < 0) return -1;
    i = jr_get(&jr, cr, "kind");
    if (is_str(i, "mutual_tls")) {
        if (jr.nodes[cr].count != 4) return bad(&e, "credentials of kind mutual_tls: expected the strings kind, ca, cert, key");
        if (str_into(&e, cr, "ca", c->ca, sizeof c->ca) || str_into(&e, cr, "cert", c->cert, sizeof c->cert) ||
            str_into(&e, cr, "key", c->key, sizeof c->key))
            return -1;
        if (check_file(&e, "ca", c->ca) || check_file(&e, "cert", c->cert) || check_file(&e, "key", c->key)) return -1;
        c->mutual_tls = 1;
    } else if (is_str(i, "none")) {
        if (jr.nodes[cr].count != 1) return bad(&e, "credentials of kind none: expected kind only");
    } else if (is_str(i, "user_password")) {
        return bad(&e, "credentials user_password: zenoh-pico cannot authenticate with a password "
                       "(use --topology router --tls-dir DIR)");
    } else {
        return bad(&e, "credentials.kind: not mutual_tls, user_password or none");
    }
    if (int_field(&e, root, "T_ns", 1, 3600LL * 1000000000LL, &v)) return -1;
    c->T_ns = v;
    if (int_field(&e, root, "n_steps", 1, 0xFFFFFFFELL, &v)) return -1;
    if (v > (long long)(INT64_MAX / 4 / c->T_ns)) return bad(&e, "n_steps: the run is too long");
    c->n_steps = (uint32_t)v;
    i = field(&e, root, "timing", J_STR, "a string");
    if (i < 0) return -1;
    if (!is_str(i, "ideal")) return bad(&e, "timing %.20s: this device runs ideal timing only", jr.nodes[i].str);
    i = field(&e, root, "ack_via_attacker", J_TRUE, "true or false");
    if (i < 0) return -1;
    c->ack_via_attacker = jr.nodes[i].type == J_TRUE;
    if (str_into(&e, root, "digest", c->digest, sizeof c->digest)) return bad(&e, "digest: expected 16 hex digits");
    if (strlen(c->digest) != 16 || strspn(c->digest, "0123456789abcdef") != 16)
        return bad(&e, "digest: expected 16 hex digits");
    i = jr_get(&jr, root, "t0_ns");
    if (jr.nodes[i].type != J_NULL && !(jr.nodes[i].type == J_NUM && jr.nodes[i].is_int))
        return bad(&e, "t0_ns: expected an integer or null");
    if (int_field(&e, root, "start_lead_ns", 0, 60LL * 1000000000LL, &v)) return -1;
    c->start_lead_ns = v;
    a = field(&e, root, "wait_ready", J_ARR, "a list of strings");
    if (a < 0) return -1;
    if (jr.nodes[a].count > MAX_WAIT) return bad(&e, "wait_ready: more than %d names", MAX_WAIT);
    for (int k = 0; k < jr.nodes[a].count; k++) {
        int s = jr_at(&jr, a, k);
        if (jr.nodes[s].type != J_STR || jr.nodes[s].len == 0 || jr.nodes[s].len >= sizeof c->wait_ready[0] ||
            strspn(jr.nodes[s].str, "abcdefghijklmnopqrstuvwxyz_-0123456789") != jr.nodes[s].len)
            return bad(&e, "wait_ready: expected a list of names");
        memcpy(c->wait_ready[k], jr.nodes[s].str, jr.nodes[s].len + 1);
    }
    c->n_wait = jr.nodes[a].count;
    i = field(&e, root, "ready_timeout_s", J_NUM, "a number");
    if (i < 0) return -1;
    c->ready_timeout_s = jr.nodes[i].num;
    if (!(c->ready_timeout_s > 0 && c->ready_timeout_s <= 1e6)) return bad(&e, "ready_timeout_s: out of range");
    int opts = field(&e, root, "run_options", J_OBJ, "an object");
    if (opts < 0) return -1;
    i = jr_get(&jr, opts, "colocate");
    if (i >= 0 && !(jr.nodes[i].type == J_NULL || (jr.nodes[i].type == J_ARR && jr.nodes[i].count == 0)))
        return bad(&e, "run_options.colocate: this device runs no other role");
    int sc = field(&e, root, "scenario", J_OBJ, "an object");
    if (sc < 0) return -1;
    return scenario(&e, c, sc, opts);
}
