/* A reader for the subset of TOML a scenario file uses: [table] and [[array]] headers, bare,
 * quoted and dotted keys, basic and literal strings (one-line and multi-line), integers and
 * floats (with _ separators, inf, nan), booleans, arrays (nested, over several lines) and inline
 * tables. Every leaf is flattened to a dotted path ("plant.params.a", "plant.x0"); a numeric array
 * of at most TV_MAX_ARR numbers is kept as one leaf. Dates are not read (a scenario has none). */
#ifndef PICO_PLANT_TOML_H
#define PICO_PLANT_TOML_H

#include <stddef.h>

#define TV_MAX_PATH 96
#define TV_MAX_STR 128
#define TV_MAX_ARR 16
#define TV_MAX_LEAVES 256

enum tvtype { TV_NUM, TV_STR, TV_BOOL, TV_NUMARR, TV_OTHER };

typedef struct {
    char path[TV_MAX_PATH];
    enum tvtype type;
    double num;
    int boolean;
    char str[TV_MAX_STR];
    double arr[TV_MAX_ARR];
    int arr_n;
} tvleaf;

typedef struct {
    tvleaf leaves[TV_MAX_LEAVES];
    int n;
    char tables[64][TV_MAX_PATH];   /* every [table] / [[array]] header seen */
    int n_tables;
    char err[160];
} tvdoc;

/* Returns 0, or -1 with doc->err set. */
int tv_parse(tvdoc *doc, const char *text, size_t len);
const tvleaf *tv_find(const tvdoc *doc, const char *path);

#endif
