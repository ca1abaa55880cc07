/* scanreg.mesh._native: the compiled kernels of the mesh layer (docs/repair.md, "Compiled kernels").
 *
 * Each kernel computes what a NumPy function of scanreg.mesh computes, with the same result, and is used in its
 * place when this module was built (scanreg.mesh.native.kernels); the NumPy function stays as the reference and
 * the fallback, and tests/test_native.py compares the two. The kernels, by section of this file:
 *
 *   box_pairs             boxes.candidate_pairs_numpy          overlapping pairs of boxes (a set; another order)
 *   sheets                broad_phase._sheets_numpy            one broad-phase level's instances and sheets
 *   cross_sheet_pairs     broad_phase._cross_sheet_pairs_numpy the face pairs a level looks at (a multiset)
 *   candidate_filter      broad_phase._candidates_among_numpy  the broad phase's end: box, shared vertex, planes
 *   fold_vertices         broad_phase.fold_vertices_numpy      fans leaving the normal cone or turning twice
 *   face_keys             intersect.face_keys_numpy            a hash of each face's corner coordinates
 *   same_corners(_at)     intersect.same_corners_numpy         triangles with the same corners (by index)
 *   face_boxes            boxes.face_boxes                     each face's box, from the vertices and faces
 *   stable_order          np.argsort(kind="stable")            of uint64 keys, by a radix sort
 *   several_fans          topology.non_manifold_vertex_mask    vertices whose corners form several fans
 *   orient2d_projections  predicates.projection_axes_numpy     non-degenerate projections, the axis dropped
 *
 * Floating-point kernels repeat the NumPy version's operations in its order and the file is compiled without
 * fused multiply-adds (pyproject.toml: -ffp-contract=off), so that they give the same bits; fold_vertices'
 * angles are glibc's atan2, which NumPy's arctan2 may differ from in the last bit (see its section).
 *
 * Every kernel checks its arguments (types, shapes, index ranges, a level's cells) before it allocates or writes
 * and raises a Python exception otherwise; the checks run before the interpreter lock is released, so the arrays
 * must not change during a call (scanreg's callers pass arrays they made). Results come back as bytearrays that
 * the Python side views with np.frombuffer. A new kernel: a section here (its loop in a *_run function, its
 * wrapper with the argument checks, a line in methods[]), the NumPy version beside its caller, and a test that
 * compares the two.
 *
 * ---- box_pairs ----
 *
 * The boxes are put in levels by their largest side (level l: side <= base * 2^l) and each level in a grid of
 * that side, keyed by the cell of each box's lower corner. Two boxes that overlap, q of level b, have
 * lo_q >= lo_p - side_q >= lo_p - w_b and lo_q <= hi_p on every axis, so q's cell lies in the block of level
 * b's grid between those bounds (taken a rounding margin wider): a box queries that block on its own level and
 * the levels below (with among, on every level), a block with more cells than its level has boxes being every
 * box of the level, and keeps the boxes that overlap it, each pair once (keep()). A level's rows of cells are
 * found by hashing. The boxes' extent must be finite (the grids number their cells in 64 bits).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define MAX_LEVELS 64

typedef struct {
    uint64_t key;  /* the cell of the box's lower corner, (x * dims_y + y) * dims_z + z */
    int64_t box;   /* the box's index */
} Entry;

typedef struct {
    uint64_t row;        /* a row of cells (x, y, *): x * dims_y + y */
    int64_t start, end;  /* its entries, at[start:end] (end 0: an empty slot) */
} Row;

typedef struct {
    int64_t n;         /* boxes in the level */
    double w;          /* its cell side */
    int64_t top[3];    /* the largest cell coordinate per axis */
    uint64_t dims[3];  /* cells per axis (top + 1) */
    Entry *at;         /* its boxes, sorted by cell key, then by index */
    Row *rows;         /* a hash table of its non-empty rows */
    uint64_t mask;     /* the table's size minus one (a power of two) */
} Level;

typedef struct {
    int64_t *data;
    int64_t n, cap;  /* pairs held, pairs room */
} Pairs;

static int push(Pairs *out, int64_t i, int64_t j) {
    if (out->n == out->cap) {
        int64_t cap = out->cap ? 2 * out->cap : 4096;
        int64_t *d = realloc(out->data, (size_t)cap * 2 * sizeof(int64_t));
        if (!d) return -1;
        out->data = d;
        out->cap = cap;
    }
    out->data[2 * out->n] = i;
    out->data[2 * out->n + 1] = j;
    out->n++;
    return 0;
}

/* Whether every x[t], t < n, lies in [0, limit). */
static int below(const int64_t *x, int64_t n, int64_t limit) {
    for (int64_t t = 0; t < n; t++)
        if (x[t] < 0 || x[t] >= limit) return 0;
    return 1;
}

/* Sorts the entries by key, stably (LSD radix sort, a byte per pass, as many passes as the largest key needs). */
static int sort_entries(Entry *at, int64_t n) {
    uint64_t most = 0;
    for (int64_t t = 0; t < n; t++) most |= at[t].key;
    Entry *tmp = malloc((size_t)(n ? n : 1) * sizeof(Entry));
    if (!tmp) return -1;
    Entry *src = at, *dst = tmp;
    for (int shift = 0; shift < 64 && (most >> shift); shift += 8) {
        int64_t count[257] = {0};
        for (int64_t t = 0; t < n; t++) count[((src[t].key >> shift) & 255) + 1]++;
        for (int b = 0; b < 256; b++) count[b + 1] += count[b];
        for (int64_t t = 0; t < n; t++) dst[count[(src[t].key >> shift) & 255]++] = src[t];
        Entry *x = src; src = dst; dst = x;
    }
    if (src != at) memcpy(at, src, (size_t)n * sizeof(Entry));
    free(tmp);
    return 0;
}

static uint64_t row_hash(uint64_t row) {
    uint64_t h = row * 0x9E3779B97F4A7C15ull;
    return h ^ (h >> 29);
}

/* The level's rows in a hash table (open addressing, at most half full). */
static int index_rows(Level *L) {
    uint64_t size = 16;
    while (size < 2 * (uint64_t)L->n) size *= 2;
    L->rows = calloc(size, sizeof(Row));
    if (!L->rows) return -1;
    L->mask = size - 1;
    for (int64_t t = 0; t < L->n;) {
        uint64_t row = L->at[t].key / L->dims[2];
        int64_t e = t;
        while (e < L->n && L->at[e].key / L->dims[2] == row) e++;
        uint64_t h = row_hash(row) & L->mask;
        while (L->rows[h].end) h = (h + 1) & L->mask;
        L->rows[h] = (Row){row, t, e};
        t = e;
    }
    return 0;
}

static const Row *find_row(const Level *L, uint64_t row) {
    for (uint64_t h = row_hash(row) & L->mask; L->rows[h].end; h = (h + 1) & L->mask)
        if (L->rows[h].row == row) return &L->rows[h];
    return NULL;
}

/* The cell of coordinate x on a grid of side w from org, clamped to [0, top]. */
static int64_t cell_of(double x, double org, double w, int64_t top) {
    double c = floor((x - org) / w);
    if (!(c >= 0)) return 0;
    if (c >= (double)top) return top;
    return (int64_t)c;
}

static int overlap(const double *lo, const double *hi, int64_t p, int64_t q) {
    for (int k = 0; k < 3; k++)
        if (!(lo[3 * p + k] <= hi[3 * q + k] && lo[3 * q + k] <= hi[3 * p + k])) return 0;
    return 1;
}

/* Whether the pair (p, q) found from p's query is kept: each pair once. With a query set (among), p's query
 * looks at every level, so a pair of two boxes in it is found from both; without, p looks at its own level and
 * the levels below, so a pair of one level is found from both and a pair across levels once. */
static int keep(int64_t p, int64_t q, int same_level, const unsigned char *among) {
    if (p == q) return 0;
    if (among) return p < q || !among[q];
    return !same_level || p < q;
}

static int query(const Level *L, const double *lo, const double *hi, const double *org, int64_t p,
                 int same_level, const unsigned char *among, Pairs *out) {
    int64_t c0[3], c1[3];
    double w = L->w;
    for (int k = 0; k < 3; k++) {
        double margin = 1e-9 * w + 8 * 1.1102230246251565e-16 * (fabs(lo[3 * p + k]) + fabs(org[k]) + w);
        c0[k] = cell_of(lo[3 * p + k] - w - margin, org[k], w, L->top[k]);
        c1[k] = cell_of(hi[3 * p + k] + margin, org[k], w, L->top[k]);
    }
    double rows = (double)(c1[0] - c0[0] + 1) * (double)(c1[1] - c0[1] + 1);
    if (rows * (double)(c1[2] - c0[2] + 1) > (double)L->n) {  /* a wide box: every box of the level */
        for (int64_t t = 0; t < L->n; t++) {
            int64_t q = L->at[t].box;
            if (keep(p, q, same_level, among) && overlap(lo, hi, p, q) && push(out, p < q ? p : q, p < q ? q : p))
                return -1;
        }
        return 0;
    }
    for (int64_t x = c0[0]; x <= c1[0]; x++)
        for (int64_t y = c0[1]; y <= c1[1]; y++) {
            uint64_t row = (uint64_t)x * L->dims[1] + (uint64_t)y;
            const Row *r = find_row(L, row);
            if (!r) continue;
            for (int64_t t = r->start; t < r->end; t++) {
                int64_t z = (int64_t)(L->at[t].key - row * L->dims[2]);
                if (z < c0[2]) continue;
                if (z > c1[2]) break;
                int64_t q = L->at[t].box;
                if (keep(p, q, same_level, among) && overlap(lo, hi, p, q)
                    && push(out, p < q ? p : q, p < q ? q : p))
                    return -1;
            }
        }
    return 0;
}

static int box_pairs_run(const double *lo, const double *hi, int64_t m, const unsigned char *among, double base,
                         Pairs *out) {
    double org[3], ext = 0;
    for (int k = 0; k < 3; k++) {
        double a = INFINITY, b = -INFINITY;
        for (int64_t i = 0; i < m; i++) {
            if (lo[3 * i + k] < a) a = lo[3 * i + k];
            if (hi[3 * i + k] > b) b = hi[3 * i + k];
        }
        org[k] = a;
        if (b - a > ext) ext = b - a;
    }
    if (!isfinite(ext)) return -2;  /* an extent beyond the doubles (or a non-finite box): the caller refuses it */
    if (!(base >= ldexp(ext, -20))) base = ldexp(ext, -20);  /* at most 2^20 + 1 cells per axis: keys fit */
    if (!(base > 0)) base = 1.0;
    int *level = malloc((size_t)(m ? m : 1) * sizeof(int));
    Level L[MAX_LEVELS];
    memset(L, 0, sizeof L);
    int n_levels = 0, rc = -1;
    if (!level) return -1;
    for (int64_t i = 0; i < m; i++) {
        double side = 0;
        for (int k = 0; k < 3; k++)
            if (hi[3 * i + k] - lo[3 * i + k] > side) side = hi[3 * i + k] - lo[3 * i + k];
        int l = 0;
        while (l < MAX_LEVELS - 1 && side > ldexp(base, l)) l++;
        level[i] = l;
        if (l + 1 > n_levels) n_levels = l + 1;
        L[l].n++;
    }
    for (int l = 0; l < n_levels; l++) {
        L[l].w = ldexp(base, l);
        L[l].at = malloc((size_t)(L[l].n ? L[l].n : 1) * sizeof(Entry));
        if (!L[l].at) goto done;
        L[l].n = 0;
    }
    for (int l = 0; l < n_levels; l++)
        for (int k = 0; k < 3; k++) {
            L[l].top[k] = (int64_t)floor(ext / L[l].w) + 1;
            L[l].dims[k] = (uint64_t)L[l].top[k] + 1;
        }
    for (int64_t i = 0; i < m; i++) {
        Level *V = &L[level[i]];
        int64_t c[3];
        for (int k = 0; k < 3; k++) c[k] = cell_of(lo[3 * i + k], org[k], V->w, V->top[k]);
        V->at[V->n++] = (Entry){((uint64_t)c[0] * V->dims[1] + (uint64_t)c[1]) * V->dims[2] + (uint64_t)c[2], i};
    }
    for (int l = 0; l < n_levels; l++)
        if (sort_entries(L[l].at, L[l].n) || index_rows(&L[l])) goto done;
    for (int64_t p = 0; p < m; p++) {
        if (among && !among[p]) continue;
        int last = among ? n_levels - 1 : level[p];
        for (int l = 0; l <= last; l++)
            if (L[l].n && query(&L[l], lo, hi, org, p, l == level[p], among, out)) goto done;
    }
    rc = 0;
done:
    for (int l = 0; l < n_levels; l++) {
        free(L[l].at);
        free(L[l].rows);
    }
    free(level);
    return rc;
}

/* ---- sheets ---- */

static int64_t find(int64_t *parent, int64_t x) {
    while (parent[x] != x) {
        parent[x] = parent[parent[x]];
        x = parent[x];
    }
    return x;
}

static void join(int64_t *parent, int64_t x, int64_t y) {
    x = find(parent, x);
    y = find(parent, y);
    if (x != y) parent[x > y ? x : y] = x < y ? x : y;  /* the smaller index is the root */
}

typedef struct {
    const int64_t *a, *span, *cnt, *f1, *f2;
    const double *nrm, *p0;
    int64_t m, e, dims[3], base[3];
    double org[3], cell;
} SheetInput;

/* Whether the plane of face i passes through the cell (x, y, z): broad_phase._on_plane's operations, in its order. */
static int on_plane(const SheetInput *in, int64_t i, const int64_t c[3]) {
    double d = 0.0, reach = 0.0, size = 0.0;
    for (int k = 0; k < 3; k++) {
        double centre = in->org[k] + ((double)(c[k] + in->base[k]) + 0.5) * in->cell;
        double nk = in->nrm[3 * i + k], pk = in->p0[3 * i + k];
        d = d + nk * (centre - pk);
        reach = reach + fabs(nk);
        size = size + fabs(nk) * (fabs(centre) + fabs(pk));
    }
    return fabs(d) <= 0.5 * in->cell * reach * (1 + 1e-9) + 1e-12 * size;
}

static int sheets_run(const SheetInput *in, int64_t *start, int64_t *face, int64_t *ckey, unsigned char *present,
                      int64_t *sheet, int64_t *n_sheets) {
    const int64_t *a = in->a, *span = in->span, *cnt = in->cnt;
    uint64_t d1 = (uint64_t)in->dims[1], d2 = (uint64_t)in->dims[2];
    int64_t t = 0;
    for (int64_t i = 0; i < in->m; i++) {  /* the instances, face by face, each face's cells x-major */
        start[i] = t;
        uint64_t fkey = ((uint64_t)a[3 * i] * d1 + (uint64_t)a[3 * i + 1]) * d2 + (uint64_t)a[3 * i + 2];
        for (int64_t ox = 0; ox < span[3 * i] && cnt[i]; ox++)
            for (int64_t oy = 0; oy < span[3 * i + 1]; oy++)
                for (int64_t oz = 0; oz < span[3 * i + 2]; oz++, t++) {
                    face[t] = i;
                    ckey[t] = (int64_t)(fkey + ((uint64_t)ox * d1 + (uint64_t)oy) * d2 + (uint64_t)oz);
                    int64_t c[3] = {a[3 * i] + ox, a[3 * i + 1] + oy, a[3 * i + 2] + oz};
                    present[t] = cnt[i] > 2 ? (unsigned char)on_plane(in, i, c) : 1;
                }
    }
    int64_t n = t;
    for (t = 0; t < n; t++) sheet[t] = t;  /* the union-find's parents */
    for (int64_t k = 0; k < in->e; k++) {  /* the joins across each manifold edge */
        int64_t g1 = in->f1[k], g2 = in->f2[k];
        if (!cnt[g1] || !cnt[g2]) continue;
        if (cnt[g1] == 1 && cnt[g2] == 1) {
            if (ckey[start[g1]] == ckey[start[g2]] && present[start[g1]] && present[start[g2]])
                join(sheet, start[g1], start[g2]);
            continue;
        }
        for (int64_t u = start[g1]; u < start[g1] + cnt[g1]; u++) {  /* each cell of g1 that g2's box touches */
            uint64_t key = (uint64_t)ckey[u];
            int64_t rel[3] = {(int64_t)(key / (d1 * d2)) - a[3 * g2], (int64_t)(key % (d1 * d2) / d2) - a[3 * g2 + 1],
                              (int64_t)(key % d2) - a[3 * g2 + 2]};
            if (rel[0] < 0 || rel[1] < 0 || rel[2] < 0 || rel[0] >= span[3 * g2] || rel[1] >= span[3 * g2 + 1]
                || rel[2] >= span[3 * g2 + 2])
                continue;
            int64_t w = start[g2] + (rel[0] * span[3 * g2 + 1] + rel[1]) * span[3 * g2 + 2] + rel[2];
            if (present[u] && present[w]) join(sheet, u, w);
        }
    }
    /* labels in the order of each component's first instance (scipy's connected_components' order) */
    for (t = 0; t < n; t++) sheet[t] = find(sheet, t);  /* each instance's root: its component's first */
    int64_t labels = 0;
    for (t = 0; t < n; t++)  /* entries before t hold labels, from t on roots; a root precedes its members */
        sheet[t] = sheet[t] == t ? labels++ : sheet[sheet[t]];
    *n_sheets = labels;
    return 0;
}

/* A C-contiguous buffer of format fmt ("q": int64, "d": float64, "B": bytes) and shape (n,) for width 0, (n, 3)
 * for width 3, (n, 3, 3) for width 9, holding `items` elements unless that is -1; else a TypeError naming it. */
/* Why sheets' input is not a level of the broad phase (NULL when it is), and its instances in all (*n): every
 * dims >= 1 with their product below 2^63; each face in it (cnt != 0) with cnt its cells in all, its block of
 * cells inside the grid; the edges' faces in range. Checked before anything is allocated or written. */
static const char *sheet_input_error(const SheetInput *in, int64_t *n) {
    uint64_t cells = 1, total = 0;
    for (int k = 0; k < 3; k++)
        if (in->dims[k] < 1 || __builtin_mul_overflow(cells, (uint64_t)in->dims[k], &cells) || cells >> 63)
            return "dims must be >= 1 with a product below 2^63";
    for (int64_t i = 0; i < in->m; i++) {
        if (in->cnt[i] == 0) continue;
        uint64_t c = 1;
        for (int k = 0; k < 3; k++) {
            int64_t a = in->a[3 * i + k], w = in->span[3 * i + k];
            if (a < 0 || w < 1 || w > in->dims[k] - a || __builtin_mul_overflow(c, (uint64_t)w, &c))
                return "a face's cells lie outside the grid";
        }
        if (in->cnt[i] < 0 || (uint64_t)in->cnt[i] != c) return "cnt is not each face's cells in all";
        if (__builtin_add_overflow(total, c, &total) || total >> 59) return "too many instances";
    }
    if (!below(in->f1, in->e, in->m) || !below(in->f2, in->e, in->m)) return "f1, f2 out of range";
    *n = (int64_t)total;
    return NULL;
}

static int get_buffer(PyObject *obj, Py_buffer *view, const char *fmt, Py_ssize_t items, const char *name,
                      int width) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return -1;
    const char *f = view->format ? view->format : "B";
    int ok = strcmp(f, fmt) == 0 || (fmt[0] == 'q' && strcmp(f, "l") == 0 && view->itemsize == 8)
             || (fmt[0] == 'B' && strcmp(f, "?") == 0);
    int nd = width == 0 ? 1 : width == 3 ? 2 : 3;
    ok = ok && view->ndim == nd && (nd < 2 || view->shape[1] == 3) && (nd < 3 || view->shape[2] == 3);
    if (!ok || (items >= 0 && view->len != items * view->itemsize)) {
        PyErr_Format(PyExc_TypeError, "scanreg.mesh._native: %s has the wrong type, shape or length (%s, %s)", name,
                     fmt[0] == 'q' ? "int64" : fmt[0] == 'd' ? "float64" : "bytes",
                     width == 0 ? "1-D" : width == 3 ? "rows of 3" : "(n, 3, 3)");
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

static PyObject *sheets(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *o[7];
    SheetInput in;
    if (!PyArg_ParseTuple(args, "OOOOOOO(LLL)(LLL)(ddd)d", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6],
                          &in.dims[0], &in.dims[1], &in.dims[2], &in.base[0], &in.base[1], &in.base[2],
                          &in.org[0], &in.org[1], &in.org[2], &in.cell))
        return NULL;
    Py_buffer b[7];
    const char *names[7] = {"a", "span", "cnt", "nrm", "p0", "f1", "f2"};
    const char *fmts[7] = {"q", "q", "q", "d", "d", "q", "q"};
    const int widths[7] = {3, 3, 0, 3, 3, 0, 0};
    int got = 0;
    PyObject *result = NULL;
    for (; got < 7; got++) {
        Py_ssize_t n = -1;
        if (got == 2) n = b[0].len / 24;
        if (got == 1 || got == 3 || got == 4) n = 3 * (b[0].len / 24);
        if (got == 6) n = b[5].len / 8;
        if (get_buffer(o[got], &b[got], fmts[got], n, names[got], widths[got]) < 0) goto out;
    }
    in.a = b[0].buf; in.span = b[1].buf; in.cnt = b[2].buf; in.nrm = b[3].buf; in.p0 = b[4].buf;
    in.f1 = b[5].buf; in.f2 = b[6].buf;
    in.m = b[0].len / 24;
    in.e = b[5].len / 8;
    int64_t n = 0;
    const char *bad = sheet_input_error(&in, &n);
    if (bad) {
        PyErr_Format(PyExc_ValueError, "sheets: %s", bad);
        goto out;
    }
    PyObject *face = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(n * 8));
    PyObject *ckey = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(n * 8));
    PyObject *present = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)n);
    PyObject *sheet = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(n * 8));
    int64_t *start = malloc((size_t)(in.m ? in.m : 1) * sizeof(int64_t));
    int64_t n_sheets = 0;
    if (face && ckey && present && sheet && start) {
        Py_BEGIN_ALLOW_THREADS
        sheets_run(&in, start, (int64_t *)PyByteArray_AS_STRING(face), (int64_t *)PyByteArray_AS_STRING(ckey),
                   (unsigned char *)PyByteArray_AS_STRING(present), (int64_t *)PyByteArray_AS_STRING(sheet),
                   &n_sheets);
        Py_END_ALLOW_THREADS
        result = Py_BuildValue("(OOOOL)", face, ckey, present, sheet, (long long)n_sheets);
    } else if (!PyErr_Occurred()) {
        PyErr_NoMemory();
    }
    free(start);
    Py_XDECREF(face);
    Py_XDECREF(ckey);
    Py_XDECREF(present);
    Py_XDECREF(sheet);
out:
    for (int k = 0; k < got; k++) PyBuffer_Release(&b[k]);
    return result;
}


/* ---- cross_sheet_pairs ---- */

/* Sorts the positions pos[0:n] by key[pos] (unsigned), stably: an LSD radix sort, a byte per pass, skipping the
 * bytes where every key agrees (the same order: a stable sort's is unique). */
static int sort_by_key(int64_t *pos, int64_t n, const uint64_t *key) {
    uint64_t all_or = 0, all_and = ~0ull;
    for (int64_t t = 0; t < n; t++) {
        all_or |= key[pos[t]];
        all_and &= key[pos[t]];
    }
    int64_t *tmp = malloc((size_t)(n ? n : 1) * sizeof(int64_t));
    if (!tmp) return -1;
    int64_t *src = pos, *dst = tmp;
    for (int shift = 0; shift < 64; shift += 8) {
        if ((((all_or ^ all_and) >> shift) & 255) == 0) continue;  /* this byte the same in every key */
        int64_t count[257] = {0};
        for (int64_t t = 0; t < n; t++) count[((key[src[t]] >> shift) & 255) + 1]++;
        for (int b = 0; b < 256; b++) count[b + 1] += count[b];
        for (int64_t t = 0; t < n; t++) dst[count[(key[src[t]] >> shift) & 255]++] = src[t];
        int64_t *x = src; src = dst; dst = x;
    }
    if (src != pos) memcpy(pos, src, (size_t)n * sizeof(int64_t));
    free(tmp);
    return 0;
}

/* Whether faces i and j of fl share a vertex index. */
static int shares(const int64_t *fl, int64_t i, int64_t j) {
    for (int x = 0; x < 3; x++)
        for (int y = 0; y < 3; y++)
            if (fl[3 * i + x] == fl[3 * j + y]) return 1;
    return 0;
}

/* broad_phase._cross_sheet_pairs: in each cell, its main sheet is its largest (ties: the lowest label); the
 * instances of a cell's other sheets (and, on the last level, of a sheet that is not a graph) are paired with every
 * instance of the cell of another sheet (of a bad sheet on the last level: with every other instance). Pairs of
 * faces, of them those whose boxes overlap (the faces' boxes lo, hi) and that share no vertex index (their
 * vertex indices fl) (broad_phase._overlapping_apart: the end's first conditions, applied there anyway). */
static int cross_run(int64_t n, const int64_t *face, const int64_t *ckey, const unsigned char *present,
                     const int64_t *sheet, int64_t n_sheets, const unsigned char *bad, int last, const double *lo,
                     const double *hi, const int64_t *fl, Pairs *out) {
    int64_t *size = calloc((size_t)(n_sheets ? n_sheets : 1), sizeof(int64_t));
    unsigned char *source = calloc((size_t)(n_sheets ? n_sheets : 1), 1);
    int64_t *pos = malloc((size_t)(n ? n : 1) * sizeof(int64_t));
    int rc = -1;
    if (!size || !source || !pos) goto done;
    for (int64_t t = 0; t < n; t++) size[sheet[t]]++;
    int64_t k = 0;
    for (int64_t t = 0; t < n; t++)
        if (present[t]) pos[k++] = t;
    /* the present instances by cell (keys >= 0), each cell's in index order */
    if (sort_by_key(pos, k, (const uint64_t *)ckey)) goto done;
    for (int64_t a = 0; a < k;) {
        int64_t b = a, main = -1;
        while (b < k && ckey[pos[b]] == ckey[pos[a]]) {
            int64_t s = sheet[pos[b]];
            if (main < 0 || size[s] > size[main] || (size[s] == size[main] && s < main)) main = s;
            b++;
        }
        int hot = 0;
        for (int64_t t = a; t < b; t++) {
            int64_t s = sheet[pos[t]];
            source[s] = s != main || (bad[s] && last);
            hot |= source[s];
        }
        for (int64_t x = a; x < b && hot; x++) {
            int64_t I = pos[x], si = sheet[I];
            if (!source[si]) continue;
            for (int64_t y = a; y < b; y++) {
                int64_t J = pos[y], sj = sheet[J];
                if (!(si != sj || (bad[si] && I != J && last))) continue;
                if (!overlap(lo, hi, face[I], face[J]) || shares(fl, face[I], face[J])) continue;
                if (push(out, face[I], face[J])) goto done;
            }
        }
        a = b;
    }
    rc = 0;
done:
    free(size);
    free(source);
    free(pos);
    return rc;
}

/* ---- candidate_filter ---- */

#define O3_BOUND ((7.0 + 56.0 * 0x1p-53) * 0x1p-53)  /* predicates._O3_BOUND: Shewchuk's orient3d bound */

/* predicates.orient3d_filter: the sign of orient3d(a, b, c, d) where the floating-point filter certifies it, else 0
 * (the same operations in the same order). */
static int orient3d_filter(const double *a, const double *b, const double *c, const double *d) {
    double adx = a[0] - d[0], ady = a[1] - d[1], adz = a[2] - d[2];
    double bdx = b[0] - d[0], bdy = b[1] - d[1], bdz = b[2] - d[2];
    double cdx = c[0] - d[0], cdy = c[1] - d[1], cdz = c[2] - d[2];
    double bc = bdx * cdy, cb = cdx * bdy, ca = cdx * ady, ac = adx * cdy, ab = adx * bdy, ba = bdx * ady;
    double det = adz * (bc - cb) + bdz * (ca - ac) + cdz * (ab - ba);
    double perm = (fabs(bc) + fabs(cb)) * fabs(adz) + (fabs(ca) + fabs(ac)) * fabs(bdz)
                  + (fabs(ab) + fabs(ba)) * fabs(cdz);
    if (fabs(det) <= O3_BOUND * perm) return 0;
    return det > 0 ? 1 : det < 0 ? -1 : 0;
}

/* Whether every corner of face q lies certainly on one side of face p's plane. */
static int separated(const double *v, const int64_t *fl, int64_t p, int64_t q) {
    const double *a = v + 3 * fl[3 * p], *b = v + 3 * fl[3 * p + 1], *c = v + 3 * fl[3 * p + 2];
    int s0 = orient3d_filter(a, b, c, v + 3 * fl[3 * q]);
    int s1 = orient3d_filter(a, b, c, v + 3 * fl[3 * q + 1]);
    int s2 = orient3d_filter(a, b, c, v + 3 * fl[3 * q + 2]);
    return (s0 > 0 && s1 > 0 && s2 > 0) || (s0 < 0 && s1 < 0 && s2 < 0);
}

/* The end of broad_phase.intersection_candidates: of the pairs (i, j) of faces fl (positions), those whose boxes
 * overlap and that share no vertex index, each once, sorted by (min, max), that no face's plane separates. */
static int filter_run(int64_t n, const int64_t *pi, const int64_t *pj, int64_t m, const double *lo,
                      const double *hi, const int64_t *fl, const double *v, Pairs *out) {
    int64_t *key = malloc((size_t)(n ? n : 1) * sizeof(int64_t));
    int64_t *pos = malloc((size_t)(n ? n : 1) * sizeof(int64_t));
    int rc = -1;
    if (!key || !pos) goto done;
    int64_t k = 0;
    for (int64_t t = 0; t < n; t++) {
        int64_t i = pi[t], j = pj[t];
        if (!overlap(lo, hi, i, j) || shares(fl, i, j)) continue;
        key[k] = (i < j ? i : j) * m + (i < j ? j : i);
        pos[k] = k;
        k++;
    }
    if (sort_by_key(pos, k, (const uint64_t *)key)) goto done;  /* (keys >= 0) */
    for (int64_t t = 0; t < k; t++) {
        int64_t kk = key[pos[t]];
        if (t && kk == key[pos[t - 1]]) continue;
        int64_t i = kk / m, j = kk % m;
        if (!separated(v, fl, i, j) && !separated(v, fl, j, i) && push(out, i, j)) goto done;
    }
    rc = 0;
done:
    free(key);
    free(pos);
    return rc;
}

/* ---- fold_vertices ---- */

#define CONE_COS 0.1

/* broad_phase.fold_vertices on live faces fl (m, 3) of nv vertices: folded[v] = 1 where the faces' normals leave
 * the cone around their mean or their corners turn more than once around v. The sums run in NumPy's order
 * (corner 0 of every face, then corner 1, then corner 2); the angles are libm's atan2 (correctly rounded in
 * glibc), which NumPy's arctan2 differs from in the last bit for some arguments (its vectorised version on
 * AVX-512 machines): only a fan whose turning lies within rounding of the margin can tell them apart. */
static int fold_run(const double *v, const int64_t *fl, int64_t m, int64_t nv, unsigned char *folded) {
    double *mean = calloc((size_t)(nv ? nv : 1) * 3, sizeof(double));
    double *turns = calloc((size_t)(nv ? nv : 1), sizeof(double));
    double *nrm = malloc((size_t)(m ? m : 1) * 3 * sizeof(double));
    double *edge = malloc((size_t)(m ? m : 1) * 9 * sizeof(double));
    int rc = -1;
    if (!mean || !turns || !nrm || !edge) goto done;
    for (int64_t i = 0; i < m; i++) {
        for (int c = 0; c < 3; c++)
            for (int k = 0; k < 3; k++)
                edge[9 * i + 3 * c + k] = v[3 * fl[3 * i + (c + 1) % 3] + k] - v[3 * fl[3 * i + c] + k];
        const double *a = edge + 9 * i, *b = edge + 9 * i + 3;
        nrm[3 * i] = a[1] * b[2] - a[2] * b[1];
        nrm[3 * i + 1] = a[2] * b[0] - a[0] * b[2];
        nrm[3 * i + 2] = a[0] * b[1] - a[1] * b[0];
    }
    for (int c = 0; c < 3; c++)
        for (int64_t i = 0; i < m; i++)
            for (int k = 0; k < 3; k++) mean[3 * fl[3 * i + c] + k] += nrm[3 * i + k];
    for (int64_t x = 0; x < nv; x++) {
        double *u = mean + 3 * x;
        double length = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
        double d = length < 1e-300 ? 1e-300 : length;  /* np.maximum(length, 1e-300), NaN kept */
        for (int k = 0; k < 3; k++) u[k] = u[k] / d;  /* the unit mean normal from here on */
    }
    for (int c = 0; c < 3; c++)
        for (int64_t i = 0; i < m; i++) {
            int64_t x = fl[3 * i + c];
            const double *n = nrm + 3 * i, *u = mean + 3 * x;
            const double *o = edge + 9 * i + 3 * c, *bk = edge + 9 * i + 3 * ((c + 2) % 3);
            double fn = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
            /* Python's sum() starts from 0: 0.0 + x turns a -0.0 into +0.0, which atan2 tells apart */
            double dot = 0.0 + n[0] * u[0] + n[1] * u[1] + n[2] * u[2];
            if (dot <= CONE_COS * fn) folded[x] = 1;
            double back[3] = {-bk[0], -bk[1], -bk[2]};
            double cos = (0.0 + o[0] * back[0] + o[1] * back[1] + o[2] * back[2])
                         - (0.0 + o[0] * u[0] + o[1] * u[1] + o[2] * u[2])
                               * (0.0 + back[0] * u[0] + back[1] * u[1] + back[2] * u[2]);
            turns[x] += atan2(dot, cos);
        }
    for (int64_t x = 0; x < nv; x++)
        if (turns[x] > 2 * 3.141592653589793 + 1e-6) folded[x] = 1;
    rc = 0;
done:
    free(mean);
    free(turns);
    free(nrm);
    free(edge);
    return rc;
}


static PyObject *box_pairs(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *lo_obj, *hi_obj, *among_obj;
    double base;
    if (!PyArg_ParseTuple(args, "OOOd", &lo_obj, &hi_obj, &among_obj, &base)) return NULL;
    Py_buffer lo, hi, among = {0};
    if (get_buffer(lo_obj, &lo, "d", -1, "lo", 3) < 0) return NULL;
    if (get_buffer(hi_obj, &hi, "d", lo.len / 8, "hi", 3) < 0) { PyBuffer_Release(&lo); return NULL; }
    int64_t m = lo.len / 24;
    PyObject *result = NULL;
    if (hi.len != lo.len) {
        PyErr_SetString(PyExc_ValueError, "box_pairs: lo and hi differ in length");
        goto out;
    }
    if (among_obj != Py_None && get_buffer(among_obj, &among, "B", m, "among", 0) < 0) {
        among.obj = NULL;  /* released by get_buffer */
        goto out;
    }
    Pairs pairs = {0};
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = box_pairs_run(lo.buf, hi.buf, m, among.buf, base, &pairs);
    Py_END_ALLOW_THREADS
    if (rc == -2) PyErr_SetString(PyExc_ValueError, "box_pairs: the boxes' extent is not finite");
    else if (rc) PyErr_NoMemory();
    else result = PyByteArray_FromStringAndSize((const char *)pairs.data,
                                                (Py_ssize_t)(pairs.n * 2 * (int64_t)sizeof(int64_t)));
    free(pairs.data);
out:
    if (among.obj) PyBuffer_Release(&among);
    PyBuffer_Release(&lo);
    PyBuffer_Release(&hi);
    return result;
}


static PyObject *pairs_result(Pairs *pairs, int rc) {
    PyObject *result = NULL;
    if (rc) PyErr_NoMemory();
    else result = PyByteArray_FromStringAndSize((const char *)pairs->data,
                                                (Py_ssize_t)(pairs->n * 2 * (int64_t)sizeof(int64_t)));
    free(pairs->data);
    return result;
}

static PyObject *cross_sheet_pairs(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *o[8];
    long long n_sheets;
    int last;
    if (!PyArg_ParseTuple(args, "OOOOLOpOOO", &o[0], &o[1], &o[2], &o[3], &n_sheets, &o[4], &last, &o[5], &o[6],
                          &o[7]))
        return NULL;
    if (n_sheets < 0) {
        PyErr_SetString(PyExc_ValueError, "cross_sheet_pairs: n_sheets < 0");
        return NULL;
    }
    Py_buffer b[8];
    const char *names[8] = {"face", "ckey", "present", "sheet", "bad_sheet", "lo", "hi", "fl"};
    const char *fmts[8] = {"q", "q", "B", "q", "B", "d", "d", "q"};
    int got = 0;
    PyObject *result = NULL;
    for (; got < 8; got++) {
        Py_ssize_t n = got == 4 ? (Py_ssize_t)n_sheets : got > 5 ? b[5].len / 8 : got && got < 5 ? b[0].len / 8 : -1;
        if (get_buffer(o[got], &b[got], fmts[got], n, names[got], got < 5 ? 0 : 3) < 0) goto out;
    }
    int64_t n = b[0].len / 8;
    const int64_t *sheet = b[3].buf;
    if (!below(sheet, n, n_sheets) || !below(b[0].buf, n, b[5].len / 24)) {
        PyErr_SetString(PyExc_ValueError, "cross_sheet_pairs: a sheet label or a face out of range");
        goto out;
    }
    Pairs pairs = {0};
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = cross_run(n, b[0].buf, b[1].buf, b[2].buf, sheet, n_sheets, b[4].buf, last, b[5].buf, b[6].buf, b[7].buf,
                   &pairs);
    Py_END_ALLOW_THREADS
    result = pairs_result(&pairs, rc);
out:
    for (int k = 0; k < got; k++) PyBuffer_Release(&b[k]);
    return result;
}

static PyObject *candidate_filter(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *o[6];
    if (!PyArg_ParseTuple(args, "OOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5])) return NULL;
    Py_buffer b[6];
    const char *names[6] = {"i", "j", "lo", "hi", "fl", "v"};
    const char *fmts[6] = {"q", "q", "d", "d", "q", "d"};
    int got = 0;
    PyObject *result = NULL;
    for (; got < 6; got++) {
        Py_ssize_t n = got == 1 ? b[0].len / 8 : got == 3 || got == 4 ? b[2].len / 8 : -1;
        if (get_buffer(o[got], &b[got], fmts[got], n, names[got], got < 2 ? 0 : 3) < 0) goto out;
    }
    int64_t n = b[0].len / 8, m = b[2].len / 24, nv = b[5].len / 24;
    const int64_t *pi = b[0].buf, *pj = b[1].buf, *fl = b[4].buf;
    if (!below(pi, n, m) || !below(pj, n, m) || !below(fl, 3 * m, nv)) {
        PyErr_SetString(PyExc_ValueError, "candidate_filter: a face or vertex out of range");
        goto out;
    }
    Pairs pairs = {0};
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = filter_run(n, pi, pj, m, b[2].buf, b[3].buf, fl, b[5].buf, &pairs);
    Py_END_ALLOW_THREADS
    result = pairs_result(&pairs, rc);
out:
    for (int k = 0; k < got; k++) PyBuffer_Release(&b[k]);
    return result;
}

static PyObject *fold_vertices(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *vo, *fo;
    long long nv;
    if (!PyArg_ParseTuple(args, "OOL", &vo, &fo, &nv)) return NULL;
    Py_buffer v, f;
    if (get_buffer(vo, &v, "d", -1, "vertices", 3) < 0) return NULL;
    if (get_buffer(fo, &f, "q", -1, "faces", 3) < 0) { PyBuffer_Release(&v); return NULL; }
    PyObject *result = NULL;
    int64_t m = f.len / 24;
    const int64_t *fl = f.buf;
    if (nv < 0 || nv > v.len / 24) {
        PyErr_SetString(PyExc_ValueError, "fold_vertices: nv must be at most the vertices");
        goto out;
    }
    if (!below(fl, 3 * m, nv)) {
        PyErr_SetString(PyExc_ValueError, "fold_vertices: a vertex out of range");
        goto out;
    }
    result = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)nv);
    if (!result) goto out;
    memset(PyByteArray_AS_STRING(result), 0, (size_t)nv);
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = fold_run(v.buf, fl, m, nv, (unsigned char *)PyByteArray_AS_STRING(result));
    Py_END_ALLOW_THREADS
    if (rc) { Py_CLEAR(result); PyErr_NoMemory(); }
out:
    PyBuffer_Release(&v);
    PyBuffer_Release(&f);
    return result;
}


/* ---- face_keys, same_corners ---- */

static uint64_t mix(uint64_t z) {  /* intersect._mix: SplitMix64's finaliser */
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

/* intersect.face_keys: a hash of each face's set of corner coordinates (their bits). */
static int keys_run(const double *v, int64_t nv, const int64_t *f, int64_t m, uint64_t *out) {
    uint64_t *hv = malloc((size_t)(nv ? nv : 1) * sizeof(uint64_t));
    if (!hv) return -1;
    for (int64_t x = 0; x < nv; x++) {
        uint64_t b[3];
        memcpy(b, v + 3 * x, sizeof b);
        hv[x] = mix(b[0] ^ mix(b[1] ^ mix(b[2] ^ 0x9E3779B97F4A7C15ull)));
    }
    for (int64_t i = 0; i < m; i++) {
        uint64_t a = hv[f[3 * i]], b = hv[f[3 * i + 1]], c = hv[f[3 * i + 2]], t;
        if (a > b) { t = a; a = b; b = t; }
        if (b > c) { t = b; b = c; c = t; }
        if (a > b) { t = a; a = b; b = t; }
        out[i] = mix(a ^ mix(b ^ mix(c)));
    }
    free(hv);
    return 0;
}

static int same_point(const double *p, const double *q) { return p[0] == q[0] && p[1] == q[1] && p[2] == q[2]; }

/* intersect.same_corners: whether triangles P[i] and Q[i] (corners of 3 coordinates) have the same corners. */
static void same_run(const double *P, const double *Q, int64_t m, unsigned char *out) {
    for (int64_t i = 0; i < m; i++) {
        const double *p = P + 9 * i, *q = Q + 9 * i;
        int same = 1;
        for (int k = 0; k < 3 && same; k++)
            same = (same_point(p + 3 * k, q) || same_point(p + 3 * k, q + 3) || same_point(p + 3 * k, q + 6))
                   && (same_point(q + 3 * k, p) || same_point(q + 3 * k, p + 3) || same_point(q + 3 * k, p + 6));
        out[i] = (unsigned char)same;
    }
}

static PyObject *face_keys(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *vo, *fo;
    if (!PyArg_ParseTuple(args, "OO", &vo, &fo)) return NULL;
    Py_buffer v, f;
    if (get_buffer(vo, &v, "d", -1, "vertices", 3) < 0) return NULL;
    if (get_buffer(fo, &f, "q", -1, "faces", 3) < 0) { PyBuffer_Release(&v); return NULL; }
    PyObject *result = NULL;
    int64_t nv = v.len / 24, m = f.len / 24;
    const int64_t *fl = f.buf;
    if (!below(fl, 3 * m, nv)) {
        PyErr_SetString(PyExc_ValueError, "face_keys: a vertex out of range");
        goto out;
    }
    result = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(m * 8));
    if (!result) goto out;
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = keys_run(v.buf, nv, fl, m, (uint64_t *)PyByteArray_AS_STRING(result));
    Py_END_ALLOW_THREADS
    if (rc) { Py_CLEAR(result); PyErr_NoMemory(); }
out:
    PyBuffer_Release(&v);
    PyBuffer_Release(&f);
    return result;
}

static PyObject *same_corners(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *po, *qo;
    if (!PyArg_ParseTuple(args, "OO", &po, &qo)) return NULL;
    Py_buffer P, Q;
    if (get_buffer(po, &P, "d", -1, "P", 9) < 0) return NULL;
    if (get_buffer(qo, &Q, "d", P.len / 8, "Q", 9) < 0) { PyBuffer_Release(&P); return NULL; }
    PyObject *result = NULL;
    int64_t m = P.len / 72;
    result = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)m);
    if (!result) goto out;
    Py_BEGIN_ALLOW_THREADS
    same_run(P.buf, Q.buf, m, (unsigned char *)PyByteArray_AS_STRING(result));
    Py_END_ALLOW_THREADS
out:
    PyBuffer_Release(&P);
    PyBuffer_Release(&Q);
    return result;
}



/* same_corners of faces given by index: face fa[ia[t]] of the vertices va against face fb[ib[t]] of vb (the
 * triangles are not gathered first: the gathers cost ten times the comparison). */
static void same_at_run(const double *va, const int64_t *fa, const int64_t *ia, const double *vb, const int64_t *fb,
                        const int64_t *ib, int64_t n, unsigned char *out) {
    for (int64_t t = 0; t < n; t++) {
        const int64_t *x = fa + 3 * ia[t], *y = fb + 3 * ib[t];
        const double *p[3] = {va + 3 * x[0], va + 3 * x[1], va + 3 * x[2]};
        const double *q[3] = {vb + 3 * y[0], vb + 3 * y[1], vb + 3 * y[2]};
        int same = 1;
        for (int k = 0; k < 3 && same; k++)
            same = (same_point(p[k], q[0]) || same_point(p[k], q[1]) || same_point(p[k], q[2]))
                   && (same_point(q[k], p[0]) || same_point(q[k], p[1]) || same_point(q[k], p[2]));
        out[t] = (unsigned char)same;
    }
}

/* Whether every index[t] is a face of f (m rows) whose corners are vertices of v (nv rows). */
static int faces_in_range(const int64_t *f, int64_t m, int64_t nv, const int64_t *index, int64_t n) {
    for (int64_t t = 0; t < n; t++) {
        if (index[t] < 0 || index[t] >= m) return 0;
        for (int k = 0; k < 3; k++)
            if (f[3 * index[t] + k] < 0 || f[3 * index[t] + k] >= nv) return 0;
    }
    return 1;
}

static PyObject *same_corners_at(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *o[6];
    if (!PyArg_ParseTuple(args, "OOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5])) return NULL;
    Py_buffer b[6];
    const char *names[6] = {"va", "fa", "ia", "vb", "fb", "ib"};
    const char *fmts[6] = {"d", "q", "q", "d", "q", "q"};
    const int widths[6] = {3, 3, 0, 3, 3, 0};
    int got = 0;
    PyObject *result = NULL;
    for (; got < 6; got++)
        if (get_buffer(o[got], &b[got], fmts[got], got == 5 ? b[2].len / 8 : -1, names[got], widths[got]) < 0)
            goto out;
    int64_t n = b[2].len / 8;
    if (!faces_in_range(b[1].buf, b[1].len / 24, b[0].len / 24, b[2].buf, n)
        || !faces_in_range(b[4].buf, b[4].len / 24, b[3].len / 24, b[5].buf, n)) {
        PyErr_SetString(PyExc_ValueError, "same_corners_at: a face or vertex out of range");
        goto out;
    }
    result = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)n);
    if (!result) goto out;
    Py_BEGIN_ALLOW_THREADS
    same_at_run(b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, n,
                (unsigned char *)PyByteArray_AS_STRING(result));
    Py_END_ALLOW_THREADS
out:
    for (int k = 0; k < got; k++) PyBuffer_Release(&b[k]);
    return result;
}


/* ---- face_boxes ---- */

/* boxes.face_boxes of the faces f of the vertices v: each face's box (the corners' minimum and maximum per
 * axis, as np.minimum / np.maximum take them: a NaN corner gives NaN), without gathering the corners first. */
static void boxes_run(const double *v, const int64_t *f, int64_t m, double *lo, double *hi) {
    for (int64_t i = 0; i < m; i++)
        for (int k = 0; k < 3; k++) {
            double a = v[3 * f[3 * i] + k], b = v[3 * f[3 * i + 1] + k], c = v[3 * f[3 * i + 2] + k];
            double l = a < b || a != a ? a : b, h = a > b || a != a ? a : b;  /* np.minimum: NaN propagates */
            lo[3 * i + k] = l < c || l != l ? l : c;
            hi[3 * i + k] = h > c || h != h ? h : c;
        }
}

static PyObject *face_boxes(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *vo, *fo;
    if (!PyArg_ParseTuple(args, "OO", &vo, &fo)) return NULL;
    Py_buffer v, f;
    if (get_buffer(vo, &v, "d", -1, "vertices", 3) < 0) return NULL;
    if (get_buffer(fo, &f, "q", -1, "faces", 3) < 0) { PyBuffer_Release(&v); return NULL; }
    PyObject *result = NULL, *lo = NULL, *hi = NULL;
    int64_t m = f.len / 24, nv = v.len / 24;
    const int64_t *fl = f.buf;
    if (!below(fl, 3 * m, nv)) {
        PyErr_SetString(PyExc_ValueError, "face_boxes: a vertex out of range");
        goto out;
    }
    lo = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(m * 24));
    hi = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(m * 24));
    if (!lo || !hi) goto out;
    Py_BEGIN_ALLOW_THREADS
    boxes_run(v.buf, fl, m, (double *)PyByteArray_AS_STRING(lo), (double *)PyByteArray_AS_STRING(hi));
    Py_END_ALLOW_THREADS
    result = PyTuple_Pack(2, lo, hi);
out:
    Py_XDECREF(lo);
    Py_XDECREF(hi);
    PyBuffer_Release(&v);
    PyBuffer_Release(&f);
    return result;
}

/* ---- stable_order ---- */

/* np.argsort(keys, kind="stable") of uint64 keys (sort_by_key of every position). */
static int order_run(const uint64_t *key, int64_t n, int64_t *order) {
    for (int64_t t = 0; t < n; t++) order[t] = t;
    return sort_by_key(order, n, key);
}

static PyObject *stable_order(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *ko;
    if (!PyArg_ParseTuple(args, "O", &ko)) return NULL;
    Py_buffer k;
    if (PyObject_GetBuffer(ko, &k, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return NULL;
    PyObject *result = NULL;
    if (k.itemsize != 8 || !k.format || (strcmp(k.format, "Q") != 0 && strcmp(k.format, "L") != 0) || k.ndim != 1) {
        PyErr_SetString(PyExc_TypeError, "stable_order: keys must be 1-D C-contiguous uint64");
        goto out;
    }
    int64_t n = k.len / 8;
    result = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(n * 8));
    if (!result) goto out;
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = order_run(k.buf, n, (int64_t *)PyByteArray_AS_STRING(result));
    Py_END_ALLOW_THREADS
    if (rc) { Py_CLEAR(result); PyErr_NoMemory(); }
out:
    PyBuffer_Release(&k);
    return result;
}


/* ---- several_fans ---- */

/* topology.non_manifold_vertex_mask's groups: the corners of each vertex joined across every edge with two faces
 * (rows r1[k], r2[k] of the directed edge table: local edge j = r / nf of face r % nf runs from corner j to
 * corner j + 1), corner to corner of the same vertex; out[v] = 1 where v's corners fall into more than one group. */
static int fans_run(const int64_t *f, int64_t nf, const int64_t *r1, const int64_t *r2, int64_t e, int64_t nv,
                    unsigned char *out) {
    int64_t nc = 3 * nf;
    int64_t *parent = malloc((size_t)(nc ? nc : 1) * sizeof(int64_t));
    int64_t *first = malloc((size_t)(nv ? nv : 1) * sizeof(int64_t));
    if (!parent || !first) { free(parent); free(first); return -1; }
    for (int64_t c = 0; c < nc; c++) parent[c] = c;
    for (int64_t k = 0; k < e; k++) {
        int64_t j1 = r1[k] / nf, k1 = r1[k] % nf, j2 = r2[k] / nf, k2 = r2[k] % nf;
        int64_t c1s = 3 * k1 + j1, c1e = 3 * k1 + (j1 + 1) % 3, c2s = 3 * k2 + j2, c2e = 3 * k2 + (j2 + 1) % 3;
        if (f[c1s] == f[c2s]) {  /* traversed the same way (inconsistent orientation): start with start */
            join(parent, c1s, c2s);
            join(parent, c1e, c2e);
        } else {
            join(parent, c1s, c2e);
            join(parent, c1e, c2s);
        }
    }
    for (int64_t x = 0; x < nv; x++) first[x] = -1;
    for (int64_t c = 0; c < nc; c++) {
        int64_t r = find(parent, c), x = f[c];
        if (first[x] < 0) first[x] = r;
        else if (first[x] != r) out[x] = 1;
    }
    free(parent);
    free(first);
    return 0;
}

static PyObject *several_fans(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *fo, *ao, *bo;
    long long nv;
    if (!PyArg_ParseTuple(args, "OOOL", &fo, &ao, &bo, &nv)) return NULL;
    Py_buffer f, a, b;
    if (get_buffer(fo, &f, "q", -1, "faces", 3) < 0) return NULL;
    if (get_buffer(ao, &a, "q", -1, "r1", 0) < 0) { PyBuffer_Release(&f); return NULL; }
    if (get_buffer(bo, &b, "q", a.len / 8, "r2", 0) < 0) { PyBuffer_Release(&f); PyBuffer_Release(&a); return NULL; }
    PyObject *result = NULL;
    int64_t nf = f.len / 24, e = a.len / 8;
    const int64_t *fl = f.buf, *r1 = a.buf, *r2 = b.buf;
    if (nv < 0) {
        PyErr_SetString(PyExc_ValueError, "several_fans: nv < 0");
        goto out;
    }
    if (!below(fl, 3 * nf, nv) || !below(r1, e, 3 * nf) || !below(r2, e, 3 * nf)) {
        PyErr_SetString(PyExc_ValueError, "several_fans: a vertex or an edge row out of range");
        goto out;
    }
    result = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)nv);
    if (!result) goto out;
    memset(PyByteArray_AS_STRING(result), 0, (size_t)nv);
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = fans_run(fl, nf, r1, r2, e, nv, (unsigned char *)PyByteArray_AS_STRING(result));
    Py_END_ALLOW_THREADS
    if (rc) { Py_CLEAR(result); PyErr_NoMemory(); }
out:
    PyBuffer_Release(&f);
    PyBuffer_Release(&a);
    PyBuffer_Release(&b);
    return result;
}


/* ---- orient2d_projections ---- */

#define O2_BOUND ((3.0 + 16.0 * 0x1p-53) * 0x1p-53)  /* predicates._O2_BOUND: Shewchuk's orient2d bound */

/* predicates.projection_axes: per triangle p, q, r and per dropped axis k, the sign of det[a - c; b - c] of the
 * corners projected on the other two axes where Shewchuk's bound certifies it (the same operations in the same
 * order as predicates.orient2d), 2 where it cannot (the caller decides those rows exactly); and where all three
 * are certain, the axis projection_axes drops. */
/* Shewchuk's Two_Diff: whether a - b is exact in floating point (its rounding error zero). */
static int exact_diff(double a, double b) {
    double x = a - b, bvirt = a - x, avirt = x + bvirt, bround = bvirt - b, around = a - avirt;
    return around + bround == 0;
}

/* The exact sign of an orient2d the filter left unsure, where it is cheap: no difference from c below 1e-150 but
 * zeros (so no product underflows: a zero permanent is a zero determinant, as predicates.orient2d decides), and
 * every difference and both products exact in floating point (then det = left - right exactly, and its sign is
 * the comparison of the two). 2 otherwise: the caller's exact arithmetic decides. Scans read from float32 files
 * (24-bit mantissas) mostly fall in the second case. */
static signed char orient2d_exact_cases(const double *a, const double *b, const double *c, int x, int y,
                                        double left, double right) {
    double d[4] = {a[x] - c[x], b[y] - c[y], a[y] - c[y], b[x] - c[x]};
    for (int t = 0; t < 4; t++)
        if (!(d[t] == 0 || fabs(d[t]) > 1e-150)) return 2;
    if (left == 0 && right == 0) return 0;  /* (the permanent is zero: orient2d's zero case) */
    if (!exact_diff(a[x], c[x]) || !exact_diff(b[y], c[y]) || !exact_diff(a[y], c[y]) || !exact_diff(b[x], c[x]))
        return 2;
    if (fma(d[0], d[1], -left) != 0 || fma(d[2], d[3], -right) != 0) return 2;
    return left > right ? 1 : left < right ? -1 : 0;
}

static void proj_run(const double *p, const double *q, const double *r, int64_t m, signed char *out,
                     signed char *drop) {
    static const int keep[3][2] = {{1, 2}, {0, 2}, {0, 1}};
    for (int64_t i = 0; i < m; i++) {
        const double *a = p + 3 * i, *b = q + 3 * i, *c = r + 3 * i;
        int unsure = 0;
        for (int k = 0; k < 3; k++) {
            int x = keep[k][0], y = keep[k][1];
            double left = (a[x] - c[x]) * (b[y] - c[y]);
            double right = (a[y] - c[y]) * (b[x] - c[x]);
            double det = left - right, perm = fabs(left) + fabs(right);
            out[3 * i + k] = fabs(det) <= O2_BOUND * perm ? 2 : det > 0 ? 1 : det < 0 ? -1 : 0;
            if (out[3 * i + k] == 2) out[3 * i + k] = orient2d_exact_cases(a, b, c, x, y, left, right);
            unsure |= out[3 * i + k] == 2;
        }
        /* the axis dropped: the normal's largest component among the projections that are nonzero (np.cross's
         * arithmetic, np.argmax's first maximum; score -1 for the others); -1 where a sign is unsure */
        drop[i] = -1;
        if (unsure) continue;
        double u[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]}, w[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
        double n[3] = {u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]};
        double best = 0;
        for (int k = 0; k < 3; k++) {
            double score = out[3 * i + k] ? fabs(n[k]) : -1.0;
            if (k == 0 || score > best) { best = score; drop[i] = (signed char)k; }
        }
    }
}

static PyObject *orient2d_projections(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "OOO", &o[0], &o[1], &o[2])) return NULL;
    Py_buffer b[3];
    const char *names[3] = {"p", "q", "r"};
    int got = 0;
    PyObject *result = NULL;
    for (; got < 3; got++)
        if (get_buffer(o[got], &b[got], "d", got ? b[0].len / 8 : -1, names[got], 3) < 0) goto out;
    int64_t m = b[0].len / 24;
    PyObject *sign = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(3 * m));
    PyObject *drop = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)m);
    if (sign && drop) {
        Py_BEGIN_ALLOW_THREADS
        proj_run(b[0].buf, b[1].buf, b[2].buf, m, (signed char *)PyByteArray_AS_STRING(sign),
                 (signed char *)PyByteArray_AS_STRING(drop));
        Py_END_ALLOW_THREADS
        result = PyTuple_Pack(2, sign, drop);
    }
    Py_XDECREF(sign);
    Py_XDECREF(drop);
out:
    for (int k = 0; k < got; k++) PyBuffer_Release(&b[k]);
    return result;
}

static PyMethodDef methods[] = {
    {"box_pairs", box_pairs, METH_VARARGS, "box_pairs(lo, hi, among, base) -> bytearray of int64 (i, j) rows"},
    {"cross_sheet_pairs", cross_sheet_pairs, METH_VARARGS,
     "cross_sheet_pairs(face, ckey, present, sheet, n_sheets, bad_sheet, last, lo, hi, fl) -> bytearray of int64 "
     "face pairs"},
    {"candidate_filter", candidate_filter, METH_VARARGS,
     "candidate_filter(i, j, lo, hi, fl, v) -> bytearray of int64 (i, j) rows, sorted"},
    {"fold_vertices", fold_vertices, METH_VARARGS, "fold_vertices(vertices, faces, nv) -> bytearray mask"},
    {"face_keys", face_keys, METH_VARARGS, "face_keys(vertices, faces) -> bytearray of uint64 keys"},
    {"same_corners", same_corners, METH_VARARGS, "same_corners(P, Q) -> bytearray mask"},
    {"same_corners_at", same_corners_at, METH_VARARGS,
     "same_corners_at(va, fa, ia, vb, fb, ib) -> bytearray mask: same_corners(va[fa[ia]], vb[fb[ib]])"},
    {"orient2d_projections", orient2d_projections, METH_VARARGS,
     "orient2d_projections(p, q, r) -> (signs: int8 (m, 3), 2 where unsure; dropped axis: int8 (m), -1 there)"},
    {"several_fans", several_fans, METH_VARARGS,
     "several_fans(faces, r1, r2, nv) -> bytearray mask of the vertices whose corners form several fans"},
    {"face_boxes", face_boxes, METH_VARARGS, "face_boxes(vertices, faces) -> (lo, hi): float64 (m, 3) bytearrays"},
    {"stable_order", stable_order, METH_VARARGS, "stable_order(keys) -> bytearray of int64: a stable argsort"},
    {"sheets", sheets, METH_VARARGS,
     "sheets(a, span, cnt, nrm, p0, f1, f2, dims, base, org, cell) -> (face, ckey, present, sheet, n_sheets)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_native", "scanreg's compiled mesh kernels", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__native(void) { return PyModule_Create(&module); }
