/* See toml.h. */
#include "toml.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    tvdoc *d;
    const char *p, *end, *start;
    int line;
} ts;

static int fail(ts *s, const char *fmt, ...) {
    if (s->d->err[0] == 0) {
        char msg[120];
        va_list ap;
        va_start(ap, fmt);
        vsnprintf(msg, sizeof msg, fmt, ap);
        va_end(ap);
        snprintf(s->d->err, sizeof s->d->err, "scenario TOML line %d: %s", s->line, msg);
    }
    return -1;
}

static void sp(ts *s) { /* spaces and tabs */
    while (s->p < s->end && (*s->p == ' ' || *s->p == '\t')) s->p++;
}

static void comment(ts *s) {
    if (s->p < s->end && *s->p == '#')
        while (s->p < s->end && *s->p != '\n') s->p++;
}

static void ws_nl(ts *s) { /* spaces, newlines and comments (inside arrays) */
    while (s->p < s->end) {
        sp(s);
        comment(s);
        if (s->p < s->end && (*s->p == '\n' || *s->p == '\r')) {
            if (*s->p == '\n') s->line++;
            s->p++;
            continue;
        }
        break;
    }
}

static int bare_char(char c) {
    return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_' || c == '-';
}

/* a string at s->p; copied (truncated to TV_MAX_STR - 1, flagged) into out */
static int string(ts *s, char *out, size_t cap, int *truncated) {
    char q = *s->p;
    int multi = (s->end - s->p >= 3 && s->p[1] == q && s->p[2] == q);
    size_t n = 0;
    *truncated = 0;
    s->p += multi ? 3 : 1;
    if (multi && s->p < s->end && *s->p == '\n') {
        s->line++;
        s->p++;
    }
    while (1) {
        if (s->p >= s->end) return fail(s, "unterminated string");
        char c = *s->p;
        if (multi && s->end - s->p >= 3 && s->p[0] == q && s->p[1] == q && s->p[2] == q) {
            s->p += 3;
            while (s->p < s->end && *s->p == q) { /* up to two quotes end the content */
                if (n + 1 < cap) out[n++] = q;
                s->p++;
            }
            break;
        }
        if (!multi && c == q) {
            s->p++;
            break;
        }
        if (c == '\n') {
            if (!multi) return fail(s, "newline in a string");
            s->line++;
        }
        if (c == '\\' && q == '"') { /* an escape: keep the escaped character (enough for the keys read) */
            s->p++;
            if (s->p >= s->end) return fail(s, "unterminated escape");
            c = *s->p;
            if (c == '\n') s->line++;
        }
        s->p++;
        if (n + 1 < cap) out[n++] = c;
        else *truncated = 1;
    }
    out[n] = 0;
    return 0;
}

static int key_part(ts *s, char *out, size_t cap) {
    sp(s);
    if (s->p < s->end && (*s->p == '"' || *s->p == '\'')) {
        int tr;
        if (string(s, out, cap, &tr)) return -1;
        if (tr) return fail(s, "key too long");
    } else {
        size_t n = 0;
        while (s->p < s->end && bare_char(*s->p)) {
            if (n + 1 >= cap) return fail(s, "key too long");
            out[n++] = *s->p++;
        }
        out[n] = 0;
        if (n == 0) return fail(s, "expected a key");
    }
    sp(s);
    return 0;
}

/* a dotted key appended to prefix into out */
static int key(ts *s, const char *prefix, char *out) {
    char part[TV_MAX_PATH];
    snprintf(out, TV_MAX_PATH, "%s", prefix);
    while (1) {
        if (key_part(s, part, sizeof part)) return -1;
        size_t have = strlen(out);
        if (have + strlen(part) + 2 > TV_MAX_PATH) return fail(s, "key path too long");
        if (have) strcat(out, ".");
        strcat(out, part);
        if (s->p < s->end && *s->p == '.') {
            s->p++;
            continue;
        }
        return 0;
    }
}

static tvleaf *leaf(ts *s, const char *path, enum tvtype t) {
    tvdoc *d = s->d;
    for (int i = 0; i < d->n; i++)
        if (strcmp(d->leaves[i].path, path) == 0) {
            fail(s, "%s defined twice", path);
            return NULL;
        }
    if (d->n >= TV_MAX_LEAVES) {
        fail(s, "more than %d keys", TV_MAX_LEAVES);
        return NULL;
    }
    tvleaf *l = &d->leaves[d->n++];
    memset(l, 0, sizeof *l);
    snprintf(l->path, sizeof l->path, "%s", path);
    l->type = t;
    return l;
}

static int number(ts *s, double *out) {
    char buf[64];
    size_t n = 0;
    const char *b = s->p;
    while (s->p < s->end && (bare_char(*s->p) || *s->p == '.' || *s->p == '+')) {
        if (*s->p != '_') {
            if (n + 1 >= sizeof buf) return fail(s, "number too long");
            buf[n++] = *s->p;
        }
        s->p++;
    }
    buf[n] = 0;
    if (n == 0) return fail(s, "expected a value");
    const char *q = buf;
    int neg = 0;
    if (*q == '+' || *q == '-') neg = *q++ == '-';
    if (strcmp(q, "inf") == 0) {
        *out = neg ? -INFINITY : INFINITY;
        return 0;
    }
    if (strcmp(q, "nan") == 0) {
        *out = NAN;
        return 0;
    }
    if (q[0] == '0' && (q[1] == 'x' || q[1] == 'o' || q[1] == 'b')) {
        long long v = strtoll(q + 2, NULL, q[1] == 'x' ? 16 : q[1] == 'o' ? 8 : 2);
        *out = neg ? -(double)v : (double)v;
        return 0;
    }
    for (const char *c = q; *c; c++)
        if (!((*c >= '0' && *c <= '9') || *c == '.' || *c == 'e' || *c == 'E' || *c == '+' || *c == '-')) {
            s->p = b;
            return fail(s, "not a number: %.30s", buf);
        }
    char *e;
    *out = strtod(buf, &e);
    if (*e != 0) return fail(s, "not a number: %.30s", buf);
    return 0;
}

static int value(ts *s, const char *path, int depth);

static int array(ts *s, const char *path, int depth) {
    double nums[TV_MAX_ARR];
    int n = 0, all_num = 1, count = 0;
    s->p++;
    while (1) {
        ws_nl(s);
        if (s->p >= s->end) return fail(s, "unterminated array");
        if (*s->p == ']') {
            s->p++;
            break;
        }
        char c = *s->p;
        if (c == '[' || c == '{' || c == '"' || c == '\'' || c == 't' || c == 'f') {
            all_num = 0;
            char sub[TV_MAX_PATH];
            snprintf(sub, sizeof sub, "%.80s[%d]", path, count);
            /* nested values are parsed (to find the end) but not kept */
            tvdoc *d = s->d;
            int keep = d->n;
            if (value(s, sub, depth + 1)) return -1;
            d->n = keep;
        } else {
            double v;
            if (number(s, &v)) return -1;
            if (n < TV_MAX_ARR) nums[n++] = v;
            else all_num = 0;
        }
        count++;
        ws_nl(s);
        if (s->p < s->end && *s->p == ',') {
            s->p++;
            continue;
        }
        ws_nl(s);
        if (s->p < s->end && *s->p == ']') {
            s->p++;
            break;
        }
        return fail(s, "expected ',' or ']'");
    }
    tvleaf *l = leaf(s, path, all_num ? TV_NUMARR : TV_OTHER);
    if (!l) return -1;
    if (all_num) {
        memcpy(l->arr, nums, sizeof(double) * (size_t)n);
        l->arr_n = n;
    }
    return 0;
}

static int inline_table(ts *s, const char *path, int depth) {
    s->p++;
    sp(s);
    if (s->p < s->end && *s->p == '}') {
        s->p++;
        return leaf(s, path, TV_OTHER) ? 0 : -1;
    }
    while (1) {
        char k[TV_MAX_PATH];
        if (key(s, path, k)) return -1;
        if (s->p >= s->end || *s->p != '=') return fail(s, "expected '='");
        s->p++;
        sp(s);
        if (value(s, k, depth + 1)) return -1;
        sp(s);
        if (s->p < s->end && *s->p == ',') {
            s->p++;
            continue;
        }
        if (s->p < s->end && *s->p == '}') {
            s->p++;
            return 0;
        }
        return fail(s, "expected ',' or '}'");
    }
}

static int value(ts *s, const char *path, int depth) {
    if (depth > 16) return fail(s, "nested too deep");
    sp(s);
    if (s->p >= s->end) return fail(s, "expected a value");
    char c = *s->p;
    if (c == '[') return array(s, path, depth);
    if (c == '{') return inline_table(s, path, depth);
    if (c == '"' || c == '\'') {
        tvleaf *l = leaf(s, path, TV_STR);
        int tr;
        if (!l || string(s, l->str, sizeof l->str, &tr)) return -1;
        if (tr) l->type = TV_OTHER; /* a long string (a description): not one the device reads */
        return 0;
    }
    if (s->end - s->p >= 4 && memcmp(s->p, "true", 4) == 0 && !(s->end - s->p > 4 && bare_char(s->p[4]))) {
        s->p += 4;
        tvleaf *l = leaf(s, path, TV_BOOL);
        if (!l) return -1;
        l->boolean = 1;
        return 0;
    }
    if (s->end - s->p >= 5 && memcmp(s->p, "false", 5) == 0 && !(s->end - s->p > 5 && bare_char(s->p[5]))) {
        s->p += 5;
        return leaf(s, path, TV_BOOL) ? 0 : -1;
    }
    double v;
    if (number(s, &v)) return -1;
    tvleaf *l = leaf(s, path, TV_NUM);
    if (!l) return -1;
    l->num = v;
    return 0;
}

static int end_of_line(ts *s) {
    sp(s);
    comment(s);
    if (s->p < s->end && *s->p == '\r') s->p++;
    if (s->p < s->end && *s->p != '\n') return fail(s, "unexpected text after a value");
    if (s->p < s->end) {
        s->p++;
        s->line++;
    }
    return 0;
}

int tv_parse(tvdoc *d, const char *text, size_t len) {
    ts s = {d, text, text + len, text, 1};
    char table[TV_MAX_PATH] = "";
    d->n = 0;
    d->n_tables = 0;
    d->err[0] = 0;
    if (memchr(text, 0, len) != NULL) {
        snprintf(d->err, sizeof d->err, "scenario TOML: a NUL byte in the text");
        return -1;
    }
    while (s.p < s.end) {
        sp(&s);
        comment(&s);
        if (s.p >= s.end) break;
        if (*s.p == '\n' || *s.p == '\r') {
            if (end_of_line(&s)) return -1;
            continue;
        }
        if (*s.p == '[') {
            int arr = s.end - s.p >= 2 && s.p[1] == '[';
            s.p += arr ? 2 : 1;
            if (key(&s, "", table)) return -1;
            if (s.p >= s.end || *s.p != ']' || (arr && (s.end - s.p < 2 || s.p[1] != ']')))
                return fail(&s, "bad table header");
            s.p += arr ? 2 : 1;
            if (d->n_tables >= 64) return fail(&s, "too many tables");
            snprintf(d->tables[d->n_tables++], TV_MAX_PATH, "%s", table);
            if (end_of_line(&s)) return -1;
            continue;
        }
        char k[TV_MAX_PATH];
        if (key(&s, table, k)) return -1;
        if (s.p >= s.end || *s.p != '=') return fail(&s, "expected '='");
        s.p++;
        if (value(&s, k, 0)) return -1;
        if (end_of_line(&s)) return -1;
    }
    return 0;
}

const tvleaf *tv_find(const tvdoc *d, const char *path) {
    for (int i = 0; i < d->n; i++)
        if (strcmp(d->leaves[i].path, path) == 0) return &d->leaves[i];
    return NULL;
}
