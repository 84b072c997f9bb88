/* A small JSON reader for the join file: the whole text is parsed into a fixed pool of nodes
 * (no allocation after jr_parse), strings are unescaped into one arena. Every limit is checked:
 * nesting depth, node count, string length; invalid UTF-8 escapes, control characters, NaN and a
 * trailing garbage byte are errors. */
#ifndef PICO_PLANT_JSON_H
#define PICO_PLANT_JSON_H

#include <stddef.h>

enum jtype { J_NULL, J_FALSE, J_TRUE, J_NUM, J_STR, J_ARR, J_OBJ };

typedef struct {
    enum jtype type;
    int is_int;          /* a number without fraction or exponent that fits in long long */
    long long ival;
    double num;
    const char *str;     /* J_STR: NUL-terminated (a string with an escaped NUL is refused) */
    size_t len;
    const char *key;     /* member of an object: its name */
    int first;           /* J_ARR, J_OBJ: index of the first child, -1 none */
    int next;            /* next sibling, -1 none */
    int count;           /* J_ARR, J_OBJ: number of children */
} jnode;

#define JR_MAX_NODES 4096
#define JR_MAX_DEPTH 32

typedef struct {
    jnode nodes[JR_MAX_NODES];
    int n;
    char *arena;         /* unescaped strings (at most as long as the text) */
    size_t arena_len, arena_cap;
    char err[160];
} jreader;

/* Parse text[0..len) (the caller keeps arena alive); returns the root's index or -1 (err set). */
int jr_parse(jreader *r, const char *text, size_t len, char *arena, size_t arena_cap);
/* The member named key of object o, or -1. */
int jr_get(const jreader *r, int o, const char *key);
/* The i-th element of an array, or -1. */
int jr_at(const jreader *r, int a, int i);

#endif
