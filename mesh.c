/*
** mesh.c -- triangle meshes in: Wavefront OBJ and PLY (ascii and both
** binary byte orders), read through one byte source and one parser, either
** collected into an indexed mesh (brt_mesh_load) or streamed in chunks of
** triangles to a scene build that never holds the mesh (brt_mesh_stream).
** The formats' rules, and how polygons become triangles, are in README.md
** ("Files").  Errors name the file and the line, element or byte.
*/
#include "internal.h"
/* The in-memory parsers the tests and fuzz targets call (testing.h). */
#include "testing.h"

#include <errno.h>
#include <fcntl.h>
#include <float.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

/* ===================================================================== */
/* Meshes: shared machinery of the OBJ and PLY loaders                   */
/* ===================================================================== */
/*
** Both loaders read through one byte source (struct reader) that is either
** a memory buffer or a file read in 1 MiB chunks; the unread tail of a chunk
** (a partial line or record) is carried over to the front of the buffer
** before the next read.  So brt_mesh_load and brt_mesh_parse_* run the same
** code, and a 10-million-triangle file never has its text in memory twice.
**
** One parser, two destinations for its triangles (add_triangle):
**  - collect (brt_mesh_load, brt_mesh_parse_*): the index array grows, and
**    the result is an indexed mesh with the file's vertex indices;
**  - stream (brt_mesh_stream): each triangle's corners are looked up at
**    once and appended to a chunk of STREAM_CHUNK triangles that is handed
**    to the consumer when full.  Only the vertex positions (12 bytes per
**    vertex), the read buffer and one chunk are held, never the indices.
**    An OBJ face may only use vertices defined before it, so its corners
**    are always known.  A PLY file may (legally, rarely) put its faces
**    before its vertices; from the first triangle whose vertex is not read
**    yet, the stream collects indices instead and emits those triangles
**    after the last element (numbering unchanged): such a file costs its
**    index array, as with brt_mesh_load.
** Both give the same triangles, numbers and messages.
**
** Limits and decisions, written down because users depend on them:
**  - Zero triangles is an error ("no triangles"): every program needs some.
**  - OBJ indices refer to vertices defined earlier in the file (positive
**    ones too), so every bad index is reported at the line that uses it.
**  - An OBJ "v" line may carry up to 4 more numbers (w, or r g b [a]
**    vertex colours); they are read and ignored.
**  - OBJ statements of the OBJ specification other than v and f are
**    ignored; an unknown statement is garbage and an error.  '#' starts
**    a comment anywhere on a line.
**  - ASCII PLY has one element per line (as every writer does); integer
**    values must fit their declared type.
**  - Vertex and triangle counts stay below 2^32 - 1 (0xFFFFFFFF is the
**    miss record's prim).  Header counts are never trusted for
**    allocation: arrays grow with the data actually read.
**  - Numbers parse exactly as strtof does in the C locale (decimal only,
**    at most 127 characters); decimals of up to 15 digits, which is what
**    exporters write, take exact fast paths (parse_float).
*/

/* TUNABLES: no parsed byte depends on them. */
#define READ_CHUNK ((size_t)1 << 20)   /* bytes per read(): large reads, small buffer */
#define STREAM_CHUNK 65536u   /* triangles per chunk a stream emits: a consumer's
                              ** call per chunk, 2.25 MiB of triangles */

typedef struct reader {
    int fd;                     /* -1: the whole input is already in data */
    const unsigned char *data;  /* unread bytes are data[pos .. end) */
    unsigned char *owned;       /* data's buffer when reading a file */
    size_t pos, end, cap;
    int eof;
} reader;

enum { WHERE_NONE, WHERE_LINE, WHERE_ELEMENT };

typedef struct parser {
    reader in;
    const char *name;           /* file name for messages */
    brt_error *err;
    int where;                  /* which location messages give */
    uint64_t line;              /* current line (text) */
    const char *element;        /* current element and record (binary PLY) */
    uint64_t record;
    /* the mesh under construction */
    float *positions;
    size_t vertex_count, vertex_cap;
    size_t triangle_count;      /* triangles numbered so far */
    /* collected triangles: the last indexed_count numbered */
    uint32_t *indices;
    size_t indexed_count, indexed_cap;
    /* streaming (emit != NULL): the chunk of corners not yet emitted */
    brt_triangle_fn emit;
    void *emit_user;
    float *chunk;
    uint32_t chunk_count;
    int deferring;              /* a vertex was missing: collect from now on */
    /* the polygon being read, as 0-based vertex indices */
    uint32_t *polygon;
    size_t polygon_count, polygon_cap;
} parser;

/* Formats "NAME:LINE: reason", "NAME: element E R: reason" or "NAME: reason". */
static brt_result parse_fail(parser *p, brt_result code, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 3, 4)))
#endif
    ;
static brt_result parse_fail(parser *p, brt_result code, const char *fmt, ...)
{
    char reason[400];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(reason, sizeof reason, fmt, ap);
    va_end(ap);
    if (p->where == WHERE_LINE)
        return brt_fail(p->err, code, "%s:%llu: %s", p->name,
                        (unsigned long long)p->line, reason);
    if (p->where == WHERE_ELEMENT)
        return brt_fail(p->err, code, "%s: element %s %llu: %s", p->name,
                        p->element, (unsigned long long)p->record, reason);
    return brt_fail(p->err, code, "%s: %s", p->name, reason);
}

/* ---- byte source ------------------------------------------------------ */

/* Makes at least need unread bytes available unless the input ends first:
** the unread tail moves to the front of the buffer, which grows only when
** one line or record is longer than it, and read() appends after it. */
static brt_result reader_fill(parser *p, size_t need)
{
    reader *r = &p->in;
    if (r->end - r->pos >= need || r->eof) return BRT_OK;
    memmove(r->owned, r->owned + r->pos, r->end - r->pos);
    r->end -= r->pos;
    r->pos = 0;
    if (need > r->cap) {
        void *bigger = brt_grow(r->owned, &r->cap, need, 1);
        if (!bigger) return parse_fail(p, BRT_ENOMEM, "out of memory");
        r->owned = bigger;
    }
    r->data = r->owned;
    while (r->end < need && !r->eof) {
        ssize_t n = read(r->fd, r->owned + r->end, r->cap - r->end);
        if (n < 0 && errno == EINTR) continue;
        if (n < 0)
            return brt_fail(p->err, BRT_EIO, "%s: read error: %s", p->name, strerror(errno));
        if (n == 0) r->eof = 1;
        r->end += (size_t)n;
    }
    return BRT_OK;
}

/* The next line without its '\n' (*got = 0 at the end of the input). */
static brt_result reader_line(parser *p, const char **line, const char **line_end, int *got)
{
    reader *r = &p->in;
    size_t scanned = 0;
    for (;;) {
        const unsigned char *start = r->data + r->pos;
        const unsigned char *nl = memchr(start + scanned, '\n', r->end - r->pos - scanned);
        brt_result rc;
        if (nl || r->eof) {
            const unsigned char *stop = nl ? nl : r->data + r->end;
            *got = nl != NULL || stop > start;
            *line = (const char *)start;
            *line_end = (const char *)stop;
            r->pos = nl ? (size_t)(nl + 1 - r->data) : r->end;
            p->line += (uint64_t)*got;
            return BRT_OK;
        }
        scanned = r->end - r->pos;   /* no '\n' yet: read on, keep the part */
        rc = reader_fill(p, scanned + 1);
        if (rc) return rc;
    }
}

/* The next n bytes (binary PLY), or a "truncated" error. */
static brt_result reader_bytes(parser *p, size_t n, const unsigned char **bytes)
{
    brt_result rc = reader_fill(p, n);
    if (rc) return rc;
    if (p->in.end - p->in.pos < n) return parse_fail(p, BRT_EPARSE, "file truncated");
    *bytes = p->in.data + p->in.pos;
    p->in.pos += n;
    return BRT_OK;
}

/* ---- the mesh under construction -------------------------------------- */

static brt_result add_vertex(parser *p, const float xyz[3])
{
    if (p->vertex_count == p->vertex_cap) {
        void *bigger;
        if (p->vertex_count >= MAX_COUNT) return parse_fail(p, BRT_EPARSE, "too many vertices");
        bigger = brt_grow(p->positions, &p->vertex_cap, p->vertex_count + 1, 3 * sizeof(float));
        if (!bigger) return parse_fail(p, BRT_ENOMEM, "out of memory");
        p->positions = bigger;
    }
    memcpy(p->positions + 3 * p->vertex_count++, xyz, 3 * sizeof(float));
    return BRT_OK;
}

/* Appends a vertex index to the polygon being read. */
static brt_result add_corner(parser *p, uint32_t vertex)
{
    if (p->polygon_count == p->polygon_cap) {
        void *bigger = brt_grow(p->polygon, &p->polygon_cap, p->polygon_count + 1, sizeof(uint32_t));
        if (!bigger) return parse_fail(p, BRT_ENOMEM, "out of memory");
        p->polygon = bigger;
    }
    p->polygon[p->polygon_count++] = vertex;
    return BRT_OK;
}

/* Hands the chunk to the consumer; its triangles are the last numbered. */
static brt_result flush_chunk(parser *p)
{
    uint32_t n = p->chunk_count;
    p->chunk_count = 0;
    if (n == 0) return BRT_OK;
    return p->emit(p->emit_user, p->chunk, n, (uint32_t)(p->triangle_count - n), p->err);
}

/* Streams the triangle when its corners are known (see the section's
** comment); 0 when it is to be collected instead. */
static int stream_triangle(parser *p, const uint32_t v[3], brt_result *rc)
{
    int c;
    if (!p->emit || p->deferring) return 0;
    if (v[0] >= p->vertex_count || v[1] >= p->vertex_count || v[2] >= p->vertex_count) {
        p->deferring = 1;
        *rc = flush_chunk(p);
        return *rc != BRT_OK;
    }
    if (!p->chunk && !(p->chunk = malloc((size_t)STREAM_CHUNK * 9 * sizeof *p->chunk))) {
        *rc = parse_fail(p, BRT_ENOMEM, "out of memory");
        return 1;
    }
    for (c = 0; c < 3; c++)
        memcpy(p->chunk + 9 * (size_t)p->chunk_count + 3 * c, p->positions + 3 * (size_t)v[c],
               3 * sizeof(float));
    p->triangle_count++;
    *rc = ++p->chunk_count == STREAM_CHUNK ? flush_chunk(p) : BRT_OK;
    return 1;
}

/* The next triangle in file order: streamed or collected. */
static brt_result add_triangle(parser *p, const uint32_t v[3])
{
    brt_result rc = BRT_OK;
    if (stream_triangle(p, v, &rc)) return rc;
    if (p->indexed_count == p->indexed_cap) {
        void *bigger = brt_grow(p->indices, &p->indexed_cap, p->indexed_count + 1, 3 * sizeof(uint32_t));
        if (!bigger) return parse_fail(p, BRT_ENOMEM, "out of memory");
        p->indices = bigger;
    }
    memcpy(p->indices + 3 * p->indexed_count++, v, 3 * sizeof(uint32_t));
    p->triangle_count++;
    return BRT_OK;
}

/* Ends the polygon being read: the fan (a,b,c), (a,c,d), ... of README.md ("Files"). */
static brt_result end_polygon(parser *p)
{
    size_t n = p->polygon_count, k;
    brt_result rc = BRT_OK;
    p->polygon_count = 0;
    if (n < 3) return parse_fail(p, BRT_EPARSE, "face with fewer than 3 vertices (%zu)", n);
    if (n - 2 > MAX_COUNT - p->triangle_count)
        return parse_fail(p, BRT_EPARSE, "too many triangles");
    for (k = 1; k + 1 < n && rc == BRT_OK; k++) {
        uint32_t tri[3];
        tri[0] = p->polygon[0];
        tri[1] = p->polygon[k];
        tri[2] = p->polygon[k + 1];
        rc = add_triangle(p, tri);
    }
    return rc;
}

/* ---- tokens and numbers ----------------------------------------------- */

static int is_blank(char c)
{
    return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
}

/* The next blank-separated token of [*cur, end); empty (s == e) at the end. */
typedef struct token { const char *s, *e; } token;

static token next_token(const char **cur, const char *end)
{
    token t;
    const char *c = *cur;
    while (c < end && is_blank(*c)) c++;
    t.s = c;
    while (c < end && !is_blank(*c)) c++;
    t.e = c;
    *cur = c;
    return t;
}

static int token_is(token t, const char *word)
{
    size_t n = strlen(word);
    return (size_t)(t.e - t.s) == n && memcmp(t.s, word, n) == 0;
}

/* A token for a message: at most 24 characters, non-printable bytes as '?'. */
static const char *shown(token t, char buf[32])
{
    size_t i, n = (size_t)(t.e - t.s) < 24 ? (size_t)(t.e - t.s) : 24;
    for (i = 0; i < n; i++) buf[i] = (t.s[i] >= 32 && t.s[i] < 127) ? t.s[i] : '?';
    strcpy(buf + n, (size_t)(t.e - t.s) > n ? "..." : "");
    return buf;
}

enum { NUMBER_OK, NUMBER_BAD, NUMBER_NOT_FINITE };

/* Reads an optionally signed decimal integer at *c, saturating at about
** 2^62 (callers reject such values as out of range).  0 without digits. */
static int scan_integer(const char **c, const char *end, int64_t *value)
{
    const char *p = *c;
    int negative = 0;
    int64_t v = 0;
    if (p < end && (*p == '+' || *p == '-')) negative = *p++ == '-';
    if (p >= end || *p < '0' || *p > '9') return 0;
    for (; p < end && *p >= '0' && *p <= '9'; p++)
        if (v < ((int64_t)1 << 58)) v = v * 10 + (*p - '0');
    *value = negative ? -v : v;
    *c = p;
    return 1;
}

/* A whole token as an integer. */
static int parse_integer(token t, int64_t *value)
{
    const char *c = t.s;
    return scan_integer(&c, t.e, value) && c == t.e;
}

/* Do the 3 characters at c spell word, ignoring case ("NaN", "Inf")? */
static int spells(const char *c, const char *word)
{
    return (c[0] | 32) == word[0] && (c[1] | 32) == word[1] && (c[2] | 32) == word[2];
}

#if defined(FLT_EVAL_METHOD) && FLT_EVAL_METHOD == 0
/* Is d, which rounds to the float f, exactly halfway between f and its
** neighbour on d's side?  (Both differences are exact in double.) */
static int is_float_midpoint(double d, float f)
{
    float g = nextafterf(f, d > f ? INFINITY : -INFINITY);
    return d - (double)f == (double)g - d;
}
#endif

/* A whole token as a float, equal to strtof's result for the same text.
** Two exact fast paths after Clinger (1990), valid when arithmetic is
** evaluated in its own type (FLT_EVAL_METHOD 0) and rounds to nearest:
**  1. m <= 2^24 and |p| <= 10, with value m * 10^p: m and 10^p are exact
**     floats, so one float multiply or divide rounds correctly.
**  2. m <= 2^53 and |p| <= 22: one double operation gives the correctly
**     rounded double d; rounding d to float is then correct unless d lies
**     exactly halfway between two floats (double rounding), and that rare
**     case, like everything else, goes to strtof on a NUL-terminated copy. */
static int parse_float(token t, float *value)
{
    static const float powers[11] = {1e0f, 1e1f, 1e2f, 1e3f, 1e4f, 1e5f,
                                     1e6f, 1e7f, 1e8f, 1e9f, 1e10f};
    static const double double_powers[23] = {
        1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11,
        1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22};
    const char *c = t.s;
    uint64_t m = 0;           /* the value is m * 10^(k + e) */
    int64_t k = 0, e = 0;
    int negative = 0, any_digit = 0, seen_point = 0;
    char copy[128];
    if (c < t.e && (*c == '+' || *c == '-')) negative = *c++ == '-';
    if (t.e - c >= 3 && (spells(c, "inf") || spells(c, "nan"))) return NUMBER_NOT_FINITE;
    for (; c < t.e; c++) {
        if (*c == '.' && !seen_point) { seen_point = 1; continue; }
        if (*c < '0' || *c > '9') break;
        any_digit = 1;
        if (m < 100000000000000000ull) {
            m = m * 10 + (uint64_t)(*c - '0');
            k -= seen_point;
        } else {
            k += !seen_point;   /* a dropped digit; m is then too big for the fast path */
        }
    }
    if (!any_digit) return NUMBER_BAD;
    if (c < t.e && (*c == 'e' || *c == 'E')) {
        c++;
        if (!scan_integer(&c, t.e, &e)) return NUMBER_BAD;
    }
    if (c != t.e) return NUMBER_BAD;
#if defined(FLT_EVAL_METHOD) && FLT_EVAL_METHOD == 0
    if (m <= (1u << 24) && k + e >= -10 && k + e <= 10) {
        float f = (float)m;
        f = k + e < 0 ? f / powers[-(k + e)] : f * powers[k + e];
        *value = negative ? -f : f;
        return NUMBER_OK;
    }
    if (m <= ((uint64_t)1 << 53) && k + e >= -22 && k + e <= 22) {
        double d = k + e < 0 ? (double)m / double_powers[-(k + e)]
                             : (double)m * double_powers[k + e];
        float f = (float)d;
        if (d > 1e-30 && d < 1e30 && ((double)f == d || !is_float_midpoint(d, f))) {
            *value = negative ? -f : f;
            return NUMBER_OK;
        }
    }
#else
    (void)powers;
    (void)double_powers;
#endif
    if ((size_t)(t.e - t.s) >= sizeof copy) return NUMBER_BAD;
    memcpy(copy, t.s, (size_t)(t.e - t.s));
    copy[t.e - t.s] = 0;
    *value = strtof(copy, NULL);
    return isfinite(*value) ? NUMBER_OK : NUMBER_NOT_FINITE;
}

/* ===================================================================== */
/* Meshes: Wavefront OBJ                                                 */
/* ===================================================================== */

/* Statements of the OBJ specification that carry no triangle geometry. */
static int obj_ignored_statement(token keyword)
{
    static const char *const ignored[] = {
        "vt", "vn", "vp", "o", "g", "s", "usemtl", "mtllib", "l", "p",
        "cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm",
        "trim", "hole", "scrv", "sp", "end", "con", "mg", "bevel",
        "c_interp", "d_interp", "lod", "maplib", "usemap", "shadow_obj",
        "trace_obj", "ctech", "stech", "call", "csh"};
    size_t i;
    for (i = 0; i < sizeof ignored / sizeof ignored[0]; i++)
        if (token_is(keyword, ignored[i])) return 1;
    return 0;
}

/* "v x y z" plus at most 4 numbers that are ignored (w, or a colour). */
static brt_result obj_vertex(parser *p, const char *c, const char *end)
{
    float xyz[3], ignored;
    char buf[32];
    int i;
    for (i = 0; i < 7; i++) {
        token t = next_token(&c, end);
        int status;
        if (t.s == t.e) {
            if (i < 3) return parse_fail(p, BRT_EPARSE, "vertex needs 3 coordinates, has %d", i);
            return add_vertex(p, xyz);
        }
        status = parse_float(t, i < 3 ? &xyz[i] : &ignored);
        if (status == NUMBER_BAD)
            return parse_fail(p, BRT_EPARSE, "bad number '%s'", shown(t, buf));
        if (status == NUMBER_NOT_FINITE && i < 3)
            return parse_fail(p, BRT_EPARSE, "coordinate '%s' is not finite", shown(t, buf));
    }
    return parse_fail(p, BRT_EPARSE, "too many values in vertex");
}

/* One corner "i", "i/t", "i//n" or "i/t/n"; only i is used.  Positive
** indices count from 1, negative ones back from the last vertex so far. */
static brt_result obj_corner(parser *p, token t)
{
    const char *c = t.s;
    int64_t i, unused;
    char buf[32];
    int slashes;
    if (!scan_integer(&c, t.e, &i)) goto bad;
    for (slashes = 0; slashes < 2 && c < t.e && *c == '/'; slashes++) {
        c++;
        if (c < t.e && *c != '/' && !scan_integer(&c, t.e, &unused)) goto bad;
    }
    if (c != t.e) goto bad;
    if (i == 0 || i > (int64_t)p->vertex_count || -i > (int64_t)p->vertex_count) {
        /* The corner as written: a huge index was capped while scanning. */
        token index = t;
        for (index.e = t.s; index.e < t.e && *index.e != '/'; index.e++) {}
        return parse_fail(p, BRT_EPARSE, "vertex index %s out of range (%zu vertices so far)",
                          shown(index, buf), p->vertex_count);
    }
    return add_corner(p, (uint32_t)(i > 0 ? i - 1 : (int64_t)p->vertex_count + i));
bad:
    return parse_fail(p, BRT_EPARSE, "bad face vertex '%s'", shown(t, buf));
}

static brt_result obj_face(parser *p, const char *c, const char *end)
{
    for (;;) {
        token t = next_token(&c, end);
        brt_result rc;
        if (t.s == t.e) return end_polygon(p);
        rc = obj_corner(p, t);
        if (rc) { p->polygon_count = 0; return rc; }
    }
}

static brt_result obj_line(parser *p, const char *c, const char *end)
{
    const char *comment = memchr(c, '#', (size_t)(end - c));
    token keyword;
    char buf[32];
    if (comment) end = comment;   /* "f 1 2 3 # note": a comment ends any line */
    keyword = next_token(&c, end);
    if (keyword.s == keyword.e) return BRT_OK;
    if (token_is(keyword, "v")) return obj_vertex(p, c, end);
    if (token_is(keyword, "f")) return obj_face(p, c, end);
    if (obj_ignored_statement(keyword)) return BRT_OK;
    return parse_fail(p, BRT_EPARSE, "unknown statement '%s'", shown(keyword, buf));
}

static brt_result obj_parse(parser *p)
{
    p->where = WHERE_LINE;
    for (;;) {
        const char *line, *end;
        int got;
        brt_result rc = reader_line(p, &line, &end, &got);
        if (rc || !got) return rc;
        rc = obj_line(p, line, end);
        if (rc) return rc;
    }
}

/* ===================================================================== */
/* Meshes: PLY (ascii, binary_little_endian, binary_big_endian)          */
/* ===================================================================== */
/*
** The header is read into a table of elements and properties, each
** property tagged with its role (x, y, z, the face's index list, or
** skipped).  One record reader then walks every element in header order
** and takes its values from either the text of a line or the binary bytes,
** so the three flavours share all of the logic above the single number.
*/

typedef enum ply_type {
    PLY_NONE, PLY_INT8, PLY_UINT8, PLY_INT16, PLY_UINT16,
    PLY_INT32, PLY_UINT32, PLY_FLOAT32, PLY_FLOAT64
} ply_type;

typedef enum ply_role { ROLE_X, ROLE_Y, ROLE_Z, ROLE_INDICES, ROLE_SKIP } ply_role;

enum { PLY_ASCII, PLY_LITTLE, PLY_BIG };
enum { ELEMENT_OTHER, ELEMENT_VERTEX, ELEMENT_FACE };

#define PLY_MAX_ELEMENTS 16
#define PLY_MAX_PROPERTIES 64

typedef struct ply_property {
    ply_type type;        /* a scalar's type, or a list's item type */
    ply_type count_type;  /* a list's count type; PLY_NONE for a scalar */
    ply_role role;
} ply_property;

typedef struct ply_element {
    char name[32];
    int kind;
    uint64_t count;
    int property_count;
    ply_property properties[PLY_MAX_PROPERTIES];
} ply_element;

typedef struct ply_header {
    int format;
    int element_count;
    ply_element elements[PLY_MAX_ELEMENTS];
    uint64_t vertex_count;
} ply_header;

/* A value as read: integer types in i, float types in f. */
typedef struct ply_value { int64_t i; float f; } ply_value;

static const struct { const char *name; ply_type type; } ply_type_names[] = {
    {"char", PLY_INT8}, {"int8", PLY_INT8}, {"uchar", PLY_UINT8}, {"uint8", PLY_UINT8},
    {"short", PLY_INT16}, {"int16", PLY_INT16}, {"ushort", PLY_UINT16}, {"uint16", PLY_UINT16},
    {"int", PLY_INT32}, {"int32", PLY_INT32}, {"uint", PLY_UINT32}, {"uint32", PLY_UINT32},
    {"float", PLY_FLOAT32}, {"float32", PLY_FLOAT32},
    {"double", PLY_FLOAT64}, {"float64", PLY_FLOAT64}};

static ply_type ply_type_named(token t)
{
    size_t i;
    for (i = 0; i < sizeof ply_type_names / sizeof ply_type_names[0]; i++)
        if (token_is(t, ply_type_names[i].name)) return ply_type_names[i].type;
    return PLY_NONE;
}

static int ply_is_integer(ply_type t) { return t >= PLY_INT8 && t <= PLY_UINT32; }

static size_t ply_type_size(ply_type t)
{
    static const size_t sizes[] = {0, 1, 1, 2, 2, 4, 4, 4, 8};
    return sizes[t];
}

/* The range of an integer type, to check ascii values against. */
static int ply_fits(ply_type t, int64_t v)
{
    static const int64_t lo[] = {0, -128, 0, -32768, 0, -2147483647 - 1, 0};
    static const int64_t hi[] = {0, 127, 255, 32767, 65535, 2147483647, 4294967295};
    return v >= lo[t] && v <= hi[t];
}

#define BAD_HEADER "bad PLY header: "

/* What a property is for: x, y, z of the vertex element must be float or
** double; the face element's vertex_indices (or vertex_index) list must be
** of integers; anything else is read and skipped. */
static brt_result ply_property_role(parser *p, const ply_element *e, ply_property *prop, token name)
{
    int is_coordinate = name.e - name.s == 1 && *name.s >= 'x' && *name.s <= 'z';
    int is_indices = token_is(name, "vertex_indices") || token_is(name, "vertex_index");
    prop->role = ROLE_SKIP;
    if (e->kind == ELEMENT_VERTEX && prop->count_type == PLY_NONE && is_coordinate) {
        if (prop->type != PLY_FLOAT32 && prop->type != PLY_FLOAT64)
            return parse_fail(p, BRT_EPARSE,
                              BAD_HEADER "vertex property %c must be float or double", *name.s);
        prop->role = (ply_role)(ROLE_X + (*name.s - 'x'));
    }
    if (e->kind == ELEMENT_FACE && prop->count_type != PLY_NONE && is_indices) {
        if (!ply_is_integer(prop->type))
            return parse_fail(p, BRT_EPARSE, BAD_HEADER "vertex indices must have an integer type");
        prop->role = ROLE_INDICES;
    }
    return BRT_OK;
}

/* "property TYPE NAME" or "property list COUNT_TYPE ITEM_TYPE NAME". */
static brt_result ply_header_property(parser *p, ply_header *h, const char *c, const char *end)
{
    ply_element *e;
    ply_property *prop;
    token type = next_token(&c, end), name;
    char buf[32];
    if (h->element_count == 0)
        return parse_fail(p, BRT_EPARSE, BAD_HEADER "property before any element");
    e = &h->elements[h->element_count - 1];
    if (e->property_count == PLY_MAX_PROPERTIES)
        return parse_fail(p, BRT_EPARSE, BAD_HEADER "more than %d properties", PLY_MAX_PROPERTIES);
    prop = &e->properties[e->property_count];
    prop->count_type = PLY_NONE;
    if (token_is(type, "list")) {
        prop->count_type = ply_type_named(next_token(&c, end));
        if (!ply_is_integer(prop->count_type))
            return parse_fail(p, BRT_EPARSE, BAD_HEADER "list count type must be an integer type");
        type = next_token(&c, end);
    }
    prop->type = ply_type_named(type);
    name = next_token(&c, end);
    if (prop->type == PLY_NONE)
        return parse_fail(p, BRT_EPARSE, BAD_HEADER "unknown type '%s'", shown(type, buf));
    if (name.s == name.e || next_token(&c, end).s != end)
        return parse_fail(p, BRT_EPARSE, BAD_HEADER "property needs a type and a name");
    e->property_count++;
    return ply_property_role(p, e, prop, name);
}

/* "element NAME COUNT". */
static brt_result ply_header_element(parser *p, ply_header *h, const char *c, const char *end)
{
    ply_element *e = &h->elements[h->element_count];
    token name = next_token(&c, end), count = next_token(&c, end);
    int64_t n;
    if (h->element_count == PLY_MAX_ELEMENTS)
        return parse_fail(p, BRT_EPARSE, BAD_HEADER "more than %d elements", PLY_MAX_ELEMENTS);
    if (name.s == name.e || !parse_integer(count, &n) || n < 0 || next_token(&c, end).s != end)
        return parse_fail(p, BRT_EPARSE, BAD_HEADER "element needs a name and a count");
    memset(e, 0, sizeof *e);
    shown(name, e->name);
    e->count = (uint64_t)n;
    e->kind = token_is(name, "vertex") ? ELEMENT_VERTEX
            : token_is(name, "face") ? ELEMENT_FACE : ELEMENT_OTHER;
    if (e->kind == ELEMENT_VERTEX) {
        if (h->vertex_count || n > MAX_COUNT)
            return parse_fail(p, BRT_EPARSE,
                              BAD_HEADER "a second vertex element or too many vertices");
        h->vertex_count = (uint64_t)n;
    }
    h->element_count++;
    return BRT_OK;
}

/* After end_header: the roles every mesh needs are present. */
static brt_result ply_header_complete(parser *p, const ply_header *h)
{
    int i, j, vertex_roles = 0, face_lists = 0;
    for (i = 0; i < h->element_count; i++)
        for (j = 0; j < h->elements[i].property_count; j++) {
            ply_role role = h->elements[i].properties[j].role;
            if (role == ROLE_INDICES) face_lists++;
            else if (role != ROLE_SKIP) vertex_roles |= 1 << role;
        }
    if (vertex_roles != 7)
        return parse_fail(p, BRT_EPARSE, BAD_HEADER "vertex element needs properties x, y and z");
    if (face_lists != 1)
        return parse_fail(p, BRT_EPARSE, BAD_HEADER "face element needs one list vertex_indices");
    return BRT_OK;
}

static brt_result ply_header_read(parser *p, ply_header *h)
{
    static const char *const formats[] = {"ascii", "binary_little_endian", "binary_big_endian"};
    int have_format = 0;
    memset(h, 0, sizeof *h);
    p->where = WHERE_LINE;
    for (;;) {
        const char *c, *end;
        token keyword;
        int got, f;
        brt_result rc = reader_line(p, &c, &end, &got);
        if (rc) return rc;
        if (!got) return parse_fail(p, BRT_EPARSE, BAD_HEADER "no end_header");
        keyword = next_token(&c, end);
        if (p->line == 1) {
            if (!token_is(keyword, "ply") || next_token(&c, end).s != end)
                return parse_fail(p, BRT_EPARSE, "not a PLY file");
        } else if (token_is(keyword, "format")) {
            token name = next_token(&c, end), version = next_token(&c, end);
            for (f = 0; f < 3 && !token_is(name, formats[f]); f++) continue;
            if (f == 3 || !token_is(version, "1.0"))
                return parse_fail(p, BRT_EPARSE, BAD_HEADER "unknown format");
            h->format = f;
            have_format = 1;
        } else if (token_is(keyword, "element")) {
            if ((rc = ply_header_element(p, h, c, end))) return rc;
        } else if (token_is(keyword, "property")) {
            if ((rc = ply_header_property(p, h, c, end))) return rc;
        } else if (token_is(keyword, "end_header")) {
            if (!have_format) return parse_fail(p, BRT_EPARSE, BAD_HEADER "no format line");
            return ply_header_complete(p, h);
        } else if (!token_is(keyword, "comment") && !token_is(keyword, "obj_info")) {
            return parse_fail(p, BRT_EPARSE, BAD_HEADER "unknown line");
        }
    }
}

/* The next value of a record: the next token of the current line (ascii)
** or the next bytes in the file's byte order (binary). */
static brt_result ply_read_value(parser *p, int format, ply_type type,
                                 const char **c, const char *end, ply_value *value)
{
    char buf[32];
    if (format == PLY_ASCII) {
        token t = next_token(c, end);
        if (t.s == t.e) return parse_fail(p, BRT_EPARSE, "too few values");
        if (ply_is_integer(type)) {
            if (parse_integer(t, &value->i) && ply_fits(type, value->i)) return BRT_OK;
        } else {
            int status = parse_float(t, &value->f);
            if (status == NUMBER_NOT_FINITE) value->f = NAN;
            if (status != NUMBER_BAD) return BRT_OK;
        }
        return parse_fail(p, BRT_EPARSE, "bad value '%s'", shown(t, buf));
    } else {
        size_t size = ply_type_size(type), i;
        const unsigned char *bytes = NULL;
        uint64_t u = 0;
        brt_result rc = reader_bytes(p, size, &bytes);
        if (rc) return rc;
        for (i = 0; i < size; i++)
            u |= (uint64_t)bytes[format == PLY_LITTLE ? i : size - 1 - i] << (8 * i);
        if (type == PLY_FLOAT64) {
            double d;
            memcpy(&d, &u, sizeof d);
            value->f = (float)d;
        } else if (type == PLY_FLOAT32) {
            uint32_t u32 = (uint32_t)u;
            memcpy(&value->f, &u32, sizeof value->f);
        } else {
            int negative = (type == PLY_INT8 || type == PLY_INT16 || type == PLY_INT32) &&
                           (u >> (8 * size - 1));
            value->i = negative ? (int64_t)u - ((int64_t)1 << (8 * size)) : (int64_t)u;
        }
        return BRT_OK;
    }
}

/* A list: the count, then the items; a vertex index list becomes a polygon. */
static brt_result ply_read_list(parser *p, int format, const ply_property *prop,
                                uint64_t vertex_count, const char **c, const char *end)
{
    ply_value count, item;
    int64_t k;
    brt_result rc = ply_read_value(p, format, prop->count_type, c, end, &count);
    if (rc) return rc;
    if (count.i < 0)
        return parse_fail(p, BRT_EPARSE, "negative list count %lld", (long long)count.i);
    if (prop->role == ROLE_INDICES && count.i < 3)
        return parse_fail(p, BRT_EPARSE, "face with fewer than 3 vertices (%lld)",
                          (long long)count.i);
    for (k = 0; k < count.i; k++) {
        if ((rc = ply_read_value(p, format, prop->type, c, end, &item))) break;
        if (prop->role != ROLE_INDICES) continue;
        if (item.i < 0 || (uint64_t)item.i >= vertex_count) {
            rc = parse_fail(p, BRT_EPARSE, "vertex index %lld out of range (%llu vertices)",
                            (long long)item.i, (unsigned long long)vertex_count);
            break;
        }
        if ((rc = add_corner(p, (uint32_t)item.i))) break;
    }
    if (rc) { p->polygon_count = 0; return rc; }
    return prop->role == ROLE_INDICES ? end_polygon(p) : BRT_OK;
}

/* The next line that holds a value (ascii records; blank lines carry none). */
static brt_result ply_ascii_line(parser *p, const ply_element *e, const char **c, const char **end)
{
    for (;;) {
        const char *probe;
        int got;
        brt_result rc = reader_line(p, c, end, &got);
        if (rc) return rc;
        if (!got) return parse_fail(p, BRT_EPARSE, "file truncated in element %s", e->name);
        probe = *c;
        if (next_token(&probe, *end).s != *end) return BRT_OK;
    }
}

/* One record of an element: one line in ascii, a run of bytes in binary. */
static brt_result ply_read_record(parser *p, const ply_header *h, const ply_element *e)
{
    const char *c = NULL, *end = NULL;
    float xyz[3] = {0, 0, 0};
    int i;
    brt_result rc = BRT_OK;
    if (h->format == PLY_ASCII && (rc = ply_ascii_line(p, e, &c, &end))) return rc;
    for (i = 0; i < e->property_count; i++) {
        const ply_property *prop = &e->properties[i];
        ply_value value = {0, 0.0f};
        if (prop->count_type != PLY_NONE)
            rc = ply_read_list(p, h->format, prop, h->vertex_count, &c, end);
        else
            rc = ply_read_value(p, h->format, prop->type, &c, end, &value);
        if (rc) return rc;
        if (prop->role <= ROLE_Z) {
            if (!isfinite(value.f))
                return parse_fail(p, BRT_EPARSE, "coordinate %c is not finite", 'x' + prop->role);
            xyz[prop->role] = value.f;
        }
    }
    if (h->format == PLY_ASCII && next_token(&c, end).s != end)
        return parse_fail(p, BRT_EPARSE, "too many values");
    return e->kind == ELEMENT_VERTEX ? add_vertex(p, xyz) : BRT_OK;
}

static brt_result ply_parse(parser *p)
{
    ply_header h;
    int i;
    brt_result rc = ply_header_read(p, &h);
    if (rc) return rc;
    if (h.format != PLY_ASCII) p->where = WHERE_ELEMENT;
    for (i = 0; i < h.element_count; i++) {
        p->element = h.elements[i].name;
        /* A binary record without properties is 0 bytes: nothing to read,
        ** however large its count (a loop over 2^32 of them would hang). */
        if (h.format != PLY_ASCII && h.elements[i].property_count == 0) continue;
        for (p->record = 0; p->record < h.elements[i].count; p->record++)
            if ((rc = ply_read_record(p, &h, &h.elements[i]))) return rc;
    }
    return BRT_OK;
}

/* ===================================================================== */
/* Meshes: entry points                                                  */
/* ===================================================================== */

enum { FORMAT_BY_CONTENT, FORMAT_OBJ, FORMAT_PLY };

static void parser_init(parser *p, const char *name, brt_error *err)
{
    memset(p, 0, sizeof *p);
    p->name = name;
    p->err = err;
    p->in.fd = -1;
}

/* "ply" on a line of its own opens every PLY file and no OBJ file. */
static int has_ply_magic(const reader *r)
{
    const unsigned char *d = r->data + r->pos;
    size_t n = r->end - r->pos;
    return n >= 4 && memcmp(d, "ply", 3) == 0 &&
           (d[3] == '\n' || (n >= 5 && d[3] == '\r' && d[4] == '\n'));
}

/* Gives back the unused part of a doubled array (keeps it if that fails). */
static void *shrink(void *items, size_t bytes)
{
    void *smaller = realloc(items, bytes);
    return smaller ? smaller : items;
}

/* Hands count triangles of an indexed mesh to emit in chunks of
** STREAM_CHUNK, numbered from number (the memory source, and a PLY
** stream's collected tail). */
static brt_result emit_indexed(const float *positions, const uint32_t *indices, size_t count,
                               size_t number, brt_triangle_fn emit, void *emit_user,
                               brt_error *err)
{
    float *corners;
    size_t done = 0;
    brt_result r = BRT_OK;
    if (count == 0) return BRT_OK;
    corners = malloc((size_t)STREAM_CHUNK * 9 * sizeof *corners);
    if (!corners) return brt_fail(err, BRT_ENOMEM, "out of memory");
    while (done < count && r == BRT_OK) {
        uint32_t n = count - done < STREAM_CHUNK ? (uint32_t)(count - done) : STREAM_CHUNK, i;
        int c;
        for (i = 0; i < n; i++)
            for (c = 0; c < 3; c++)
                memcpy(corners + 9 * (size_t)i + 3 * c,
                       positions + 3 * (size_t)indices[3 * (done + i) + (size_t)c], 3 * sizeof(float));
        r = emit(emit_user, corners, n, (uint32_t)(number + done), err);
        done += n;
    }
    free(corners);
    return r;
}

/* Runs the parser over the whole input; a stream's last chunk and its
** collected tail are emitted before "no triangles" is decided. */
static brt_result parse_input(parser *p, int format)
{
    brt_result rc = reader_fill(p, 5);
    if (rc == BRT_OK) {
        if (format == FORMAT_BY_CONTENT) format = has_ply_magic(&p->in) ? FORMAT_PLY : FORMAT_OBJ;
        rc = format == FORMAT_PLY ? ply_parse(p) : obj_parse(p);
    }
    if (rc == BRT_OK && p->emit) rc = flush_chunk(p);
    if (rc == BRT_OK && p->emit)
        rc = emit_indexed(p->positions, p->indices, p->indexed_count,
                          p->triangle_count - p->indexed_count, p->emit, p->emit_user, p->err);
    if (rc == BRT_OK && p->triangle_count == 0) {
        p->where = WHERE_NONE;
        rc = parse_fail(p, BRT_EPARSE, "no triangles");
    }
    free(p->polygon);
    free(p->chunk);
    return rc;
}

static brt_result parse_mesh(parser *p, int format, brt_mesh *mesh)
{
    brt_result rc = parse_input(p, format);
    memset(mesh, 0, sizeof *mesh);
    if (rc != BRT_OK) {
        free(p->positions);
        free(p->indices);
        return rc;
    }
    mesh->positions = shrink(p->positions, p->vertex_count * 3 * sizeof(float));
    mesh->indices = shrink(p->indices, p->triangle_count * 3 * sizeof(uint32_t));
    mesh->vertex_count = (uint32_t)p->vertex_count;
    mesh->triangle_count = (uint32_t)p->triangle_count;
    return BRT_OK;
}

static brt_result parse_memory(const char *name, const void *data, size_t size,
                               int format, brt_mesh *mesh, brt_error *err)
{
    parser p;
    parser_init(&p, name, err);
    p.in.data = data ? data : (const void *)"";
    p.in.end = data ? size : 0;
    p.in.eof = 1;
    return parse_mesh(&p, format, mesh);
}

brt_result brt_mesh_parse_obj(const char *name, const void *data, size_t size,
                              brt_mesh *mesh, brt_error *err)
{
    return parse_memory(name, data, size, FORMAT_OBJ, mesh, err);
}

brt_result brt_mesh_parse_ply(const char *name, const void *data, size_t size,
                              brt_mesh *mesh, brt_error *err)
{
    return parse_memory(name, data, size, FORMAT_PLY, mesh, err);
}

/* Opens path for the parser with a READ_CHUNK buffer. */
static brt_result parser_open(parser *p, const char *path, brt_error *err)
{
    parser_init(p, path, err);
    p->in.fd = open(path, O_RDONLY);
    if (p->in.fd < 0) return brt_fail(err, BRT_EIO, "%s: cannot open: %s", path, strerror(errno));
    p->in.owned = malloc(READ_CHUNK);
    if (!p->in.owned) {
        close(p->in.fd);
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", path);
    }
    p->in.data = p->in.owned;
    p->in.cap = READ_CHUNK;
    return BRT_OK;
}

static void parser_close(parser *p)
{
    free(p->in.owned);
    close(p->in.fd);
}

brt_result brt_mesh_load(const char *path, brt_mesh *mesh, brt_error *err)
{
    parser p;
    brt_result rc;
    memset(mesh, 0, sizeof *mesh);
    if ((rc = parser_open(&p, path, err)) != BRT_OK) return rc;
    rc = parse_mesh(&p, FORMAT_BY_CONTENT, mesh);
    parser_close(&p);
    return rc;
}

brt_result brt_mesh_stream(const char *path, brt_triangle_fn emit, void *emit_user,
                           brt_error *err)
{
    parser p;
    brt_result rc;
    if ((rc = parser_open(&p, path, err)) != BRT_OK) return rc;
    p.emit = emit;
    p.emit_user = emit_user;
    rc = parse_input(&p, FORMAT_BY_CONTENT);
    free(p.positions);
    free(p.indices);
    parser_close(&p);
    return rc;
}

void brt_mesh_free(brt_mesh *mesh)
{
    free(mesh->positions);
    free(mesh->indices);
    memset(mesh, 0, sizeof *mesh);
}

void brt_mesh_bounds(const brt_mesh *mesh, float bmin[3], float bmax[3])
{
    size_t i;
    int axis;
    for (axis = 0; axis < 3; axis++) {
        bmin[axis] = INFINITY;
        bmax[axis] = -INFINITY;
    }
    for (i = 0; i < 3 * (size_t)mesh->triangle_count; i++) {
        const float *v = mesh->positions + 3 * (size_t)mesh->indices[i];
        for (axis = 0; axis < 3; axis++) {
            if (v[axis] < bmin[axis]) bmin[axis] = v[axis];
            if (v[axis] > bmax[axis]) bmax[axis] = v[axis];
        }
    }
}

/* ---- triangle sources ------------------------------------------------- */

static brt_result file_source_run(const void *user, brt_triangle_fn emit, void *emit_user,
                                  brt_error *err)
{
    return brt_mesh_stream((const char *)user, emit, emit_user, err);
}

static brt_result memory_source_run(const void *user, brt_triangle_fn emit, void *emit_user,
                                    brt_error *err)
{
    const brt_mesh *mesh = user;
    return emit_indexed(mesh->positions, mesh->indices, mesh->triangle_count, 0, emit,
                        emit_user, err);
}

void brt_mesh_file_source(const char *path, brt_triangle_source *source)
{
    source->run = file_source_run;
    source->user = path;
}

void brt_mesh_memory_source(const brt_mesh *mesh, brt_triangle_source *source)
{
    source->run = memory_source_run;
    source->user = mesh;
}

