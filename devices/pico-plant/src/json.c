/* See json.h. RFC 8259 grammar; no extensions. */
#include "json.h"

#include <errno.h>
#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    jreader *r;
    const char *p, *end;
    const char *start;
} ps;

static int fail(ps *s, const char *fmt, ...) {
    if (s->r->err[0] == 0) {
        char msg[120];
        va_list ap;
        va_start(ap, fmt);
        vsnprintf(msg, sizeof msg, fmt, ap);
        va_end(ap);
        snprintf(s->r->err, sizeof s->r->err, "%s at byte %ld", msg, (long)(s->p - s->start));
    }
    return -1;
}

static void ws(ps *s) {
    while (s->p < s->end && (*s->p == ' ' || *s->p == '\t' || *s->p == '\n' || *s->p == '\r')) s->p++;
}

static int new_node(ps *s, enum jtype t) {
    jreader *r = s->r;
    if (r->n >= JR_MAX_NODES) return fail(s, "more than %d JSON values", JR_MAX_NODES);
    jnode *n = &r->nodes[r->n];
    memset(n, 0, sizeof *n);
    n->type = t;
    n->first = n->next = -1;
    return r->n++;
}

static int hex4(ps *s, unsigned *out) {
    unsigned v = 0;
    if (s->end - s->p < 4) return fail(s, "short \\u escape");
    for (int i = 0; i < 4; i++) {
        char c = s->p[i];
        v <<= 4;
        if (c >= '0' && c <= '9') v |= (unsigned)(c - '0');
        else if (c >= 'a' && c <= 'f') v |= (unsigned)(c - 'a' + 10);
        else if (c >= 'A' && c <= 'F') v |= (unsigned)(c - 'A' + 10);
        else return fail(s, "bad \\u escape");
    }
    s->p += 4;
    *out = v;
    return 0;
}

static int put(ps *s, char c) {
    jreader *r = s->r;
    if (r->arena_len + 1 >= r->arena_cap) return fail(s, "strings too long");
    r->arena[r->arena_len++] = c;
    return 0;
}

/* parse a string at s->p (on the opening quote) into the arena; *out, *len */
static int string(ps *s, const char **out, size_t *len) {
    s->p++;
    size_t begin = s->r->arena_len;
    while (1) {
        if (s->p >= s->end) return fail(s, "unterminated string");
        unsigned char c = (unsigned char)*s->p++;
        if (c == '"') break;
        if (c < 0x20) return fail(s, "control character in a string");
        if (c != '\\') {
            if (put(s, (char)c)) return -1;
            continue;
        }
        if (s->p >= s->end) return fail(s, "unterminated escape");
        char e = *s->p++;
        switch (e) {
            case '"': case '\\': case '/': if (put(s, e)) return -1; break;
            case 'b': if (put(s, '\b')) return -1; break;
            case 'f': if (put(s, '\f')) return -1; break;
            case 'n': if (put(s, '\n')) return -1; break;
            case 'r': if (put(s, '\r')) return -1; break;
            case 't': if (put(s, '\t')) return -1; break;
            case 'u': {
                unsigned cp, lo;
                if (hex4(s, &cp)) return -1;
                if (cp >= 0xD800 && cp <= 0xDBFF) {
                    if (s->end - s->p < 2 || s->p[0] != '\\' || s->p[1] != 'u') return fail(s, "lone surrogate");
                    s->p += 2;
                    if (hex4(s, &lo)) return -1;
                    if (lo < 0xDC00 || lo > 0xDFFF) return fail(s, "bad surrogate pair");
                    cp = 0x10000 + ((cp - 0xD800) << 10) + (lo - 0xDC00);
                } else if (cp >= 0xDC00 && cp <= 0xDFFF) {
                    return fail(s, "lone surrogate");
                }
                if (cp == 0) return fail(s, "NUL in a string");
                if (cp < 0x80) {
                    if (put(s, (char)cp)) return -1;
                } else if (cp < 0x800) {
                    if (put(s, (char)(0xC0 | (cp >> 6))) || put(s, (char)(0x80 | (cp & 0x3F)))) return -1;
                } else if (cp < 0x10000) {
                    if (put(s, (char)(0xE0 | (cp >> 12))) || put(s, (char)(0x80 | ((cp >> 6) & 0x3F))) ||
                        put(s, (char)(0x80 | (cp & 0x3F))))
                        return -1;
                } else {
                    if (put(s, (char)(0xF0 | (cp >> 18))) || put(s, (char)(0x80 | ((cp >> 12) & 0x3F))) ||
                        put(s, (char)(0x80 | ((cp >> 6) & 0x3F))) || put(s, (char)(0x80 | (cp & 0x3F))))
                        return -1;
                }
                break;
            }
            default: return fail(s, "bad escape \\%c", e);
        }
    }
    if (put(s, 0)) return -1;
    *out = s->r->arena + begin;
    *len = s->r->arena_len - begin - 1;
    return 0;
}

static int number(ps *s, int idx) {
    const char *b = s->p;
    int integral = 1;
    if (s->p < s->end && *s->p == '-') s->p++;
    if (s->p >= s->end) return fail(s, "bad number");
    if (*s->p == '0') {
        s->p++;
    } else if (*s->p >= '1' && *s->p <= '9') {
        while (s->p < s->end && *s->p >= '0' && *s->p <= '9') s->p++;
    } else {
        return fail(s, "bad number");
    }
    if (s->p < s->end && *s->p == '.') {
        integral = 0;
        s->p++;
        if (s->p >= s->end || *s->p < '0' || *s->p > '9') return fail(s, "bad number");
        while (s->p < s->end && *s->p >= '0' && *s->p <= '9') s->p++;
    }
    if (s->p < s->end && (*s->p == 'e' || *s->p == 'E')) {
        integral = 0;
        s->p++;
        if (s->p < s->end && (*s->p == '+' || *s->p == '-')) s->p++;
        if (s->p >= s->end || *s->p < '0' || *s->p > '9') return fail(s, "bad number");
        while (s->p < s->end && *s->p >= '0' && *s->p <= '9') s->p++;
    }
    char buf[64];
    size_t n = (size_t)(s->p - b);
    if (n >= sizeof buf) return fail(s, "number too long");
    memcpy(buf, b, n);
    buf[n] = 0;
    jnode *nd = &s->r->nodes[idx];
    errno = 0;
    nd->num = strtod(buf, NULL);
    if (!isfinite(nd->num)) return fail(s, "number out of range");
    if (integral) {
        errno = 0;
        long long v = strtoll(buf, NULL, 10);
        if (errno == 0) {
            nd->is_int = 1;
            nd->ival = v;
        }
    }
    return 0;
}

static int value(ps *s, int depth);

static int literal(ps *s, const char *word) {
    size_t n = strlen(word);
    if ((size_t)(s->end - s->p) < n || memcmp(s->p, word, n) != 0) return fail(s, "unexpected character");
    s->p += n;
    return 0;
}

static int value(ps *s, int depth) {
    if (depth > JR_MAX_DEPTH) return fail(s, "nested deeper than %d", JR_MAX_DEPTH);
    ws(s);
    if (s->p >= s->end) return fail(s, "unexpected end");
    char c = *s->p;
    int idx;
    if (c == '{' || c == '[') {
        int obj = c == '{';
        idx = new_node(s, obj ? J_OBJ : J_ARR);
        if (idx < 0) return -1;
        s->p++;
        ws(s);
        int last = -1;
        if (s->p < s->end && *s->p == (obj ? '}' : ']')) {
            s->p++;
            return idx;
        }
        while (1) {
            const char *key = NULL;
            size_t klen = 0;
            ws(s);
            if (obj) {
                if (s->p >= s->end || *s->p != '"') return fail(s, "expected a member name");
                if (string(s, &key, &klen)) return -1;
                for (int ch = s->r->nodes[idx].first; ch >= 0; ch = s->r->nodes[ch].next)
                    if (strcmp(s->r->nodes[ch].key, key) == 0) return fail(s, "duplicate member \"%.40s\"", key);
                ws(s);
                if (s->p >= s->end || *s->p != ':') return fail(s, "expected ':'");
                s->p++;
            }
            int ch = value(s, depth + 1);
            if (ch < 0) return -1;
            s->r->nodes[ch].key = key;
            if (last < 0) s->r->nodes[idx].first = ch;
            else s->r->nodes[last].next = ch;
            last = ch;
            s->r->nodes[idx].count++;
            ws(s);
            if (s->p >= s->end) return fail(s, "unexpected end");
            if (*s->p == ',') {
                s->p++;
                continue;
            }
            if (*s->p == (obj ? '}' : ']')) {
                s->p++;
                return idx;
            }
            return fail(s, "expected ',' or '%c'", obj ? '}' : ']');
        }
    }
    if (c == '"') {
        idx = new_node(s, J_STR);
        if (idx < 0) return -1;
        const char *str;
        size_t len;
        if (string(s, &str, &len)) return -1;
        s->r->nodes[idx].str = str;
        s->r->nodes[idx].len = len;
        return idx;
    }
    if (c == '-' || (c >= '0' && c <= '9')) {
        idx = new_node(s, J_NUM);
        if (idx < 0 || number(s, idx)) return -1;
        return idx;
    }
    if (c == 't') return literal(s, "true") ? -1 : new_node(s, J_TRUE);
    if (c == 'f') return literal(s, "false") ? -1 : new_node(s, J_FALSE);
    if (c == 'n') return literal(s, "null") ? -1 : new_node(s, J_NULL);
    return fail(s, "unexpected character");
}

int jr_parse(jreader *r, const char *text, size_t len, char *arena, size_t arena_cap) {
    ps s = {r, text, text + len, text};
    r->n = 0;
    r->arena = arena;
    r->arena_len = 0;
    r->arena_cap = arena_cap;
    r->err[0] = 0;
    if (memchr(text, 0, len) != NULL) {
        snprintf(r->err, sizeof r->err, "a NUL byte in the text");
        return -1;
    }
    int root = value(&s, 0);
    if (root < 0) return -1;
    ws(&s);
    if (s.p != s.end) return fail(&s, "trailing characters");
    return root;
}

int jr_get(const jreader *r, int o, const char *key) {
    if (o < 0 || r->nodes[o].type != J_OBJ) return -1;
    for (int c = r->nodes[o].first; c >= 0; c = r->nodes[c].next)
        if (strcmp(r->nodes[c].key, key) == 0) return c;
    return -1;
}

int jr_at(const jreader *r, int a, int i) {
    if (a < 0 || r->nodes[a].type != J_ARR || i < 0) return -1;
    int c = r->nodes[a].first;
    while (c >= 0 && i-- > 0) c = r->nodes[c].next;
    return c;
}
