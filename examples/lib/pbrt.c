/*
** examples/lib/pbrt.c -- the streaming pbrt-v4 scene reader of examples/lib/pbrt.h
** (the manual is there).  Format: pbrt-v4's scene description
** (pbrt.org/fileformat-v4); semantics checked against pbrt-v4's
** src/pbrt/parser.cpp (tokens, parameter lists), src/pbrt/scene.cpp
** (transforms, object instancing, the camera) and src/pbrt/shapes.cpp
** (loopsubdiv's parameters; its refinement is examples/lib/loopsubdiv.c).
**
** Two passes.  ex_pbrt_open (Part IV) tokenizes the file tree once,
** keeping the graphics state (a stack of transforms) and recording per
** triangle shape where its P and indices are (file, byte offset) and the
** transform in force; it checks every number then, so that the streams
** (Part V) meet no surprises unless a file changes.  The streams seek to
** the recorded offsets and read the numbers again, chunk by chunk.
**
**   Part I    numbers (as strtof reads them)
**   Part II   the tokenizer: a window over a file, seekable
**   Part III  affine transforms in double
**   Part IV   pass 1: directives
**   Part V    pass 2: the streams
**   Part VI   the public functions
*/
#include "pbrt.h"
#include "loopsubdiv.h"
#include "count.h"

#include <errno.h>
#include <fcntl.h>
#include <float.h>
#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <sys/wait.h>
#include <unistd.h>

#define CHUNK_TRIS 65536u           /* triangles per emitted chunk */
#define MAX_TOKEN ((size_t)1 << 16) /* the longest token (a string, a number) */
#define PASS1_WINDOW ((size_t)1 << 20)
#define PASS2_WINDOW ((size_t)1 << 20)
#define MAX_DEPTH 64                /* nested Includes */
#define NO_OBJECT 0xFFFFFFFFu
#define PI 3.14159265358979323846

/* ===================================================================== */
/* Part I: numbers                                                       */
/* ===================================================================== */

enum { NUM_OK, NUM_BAD, NUM_NOT_FINITE };

/* A decimal number as scanned: value = m * 10^exp10 with up to 18
** significant digits.  Past 18, m is not kept (decimal_float reads the
** text with strtof past 15) and exp10 keeps the magnitude: the value
** lies below 10^(18 + exp10). */
typedef struct decimal {
    uint64_t m;
    int digits;             /* significant digits, 19 standing for more than 18 */
    int exp10;
    int negative;
    int plain;              /* digits only: no sign, point or exponent */
} decimal;

enum { DEC_OK, DEC_NO_DIGITS, DEC_BAD_EXPONENT };

/* Decimal digits from c into *m (wrapping past 19 digits; skipped when
** values is 0, a constant where this is inlined); returns the byte after
** them.  Two digits a round: half the loop's tests. */
#if defined(__GNUC__)
static inline const char *take_digits(const char *c, uint64_t *m, int values) __attribute__((always_inline));
#endif
static inline const char *take_digits(const char *c, uint64_t *m, int values)
{
    uint64_t v = *m;
    unsigned a, b;
    while ((a = (unsigned)(unsigned char)c[0] - '0') <= 9) {
        if ((b = (unsigned)(unsigned char)c[1] - '0') > 9) { if (values) v = v * 10 + a; c++; break; }
        if (values) v = v * 100 + a * 10 + b;
        c += 2;
    }
    *m = v;
    return c;
}

/* Scans [sign] digits [. digits] [(e|E) [sign] digits] from *at, stopping
** at the first byte that cannot go on (*at then points there; with no
** digit, just after the sign and the point).  One pass over the bytes:
** the tokenizer's fast path (Part II) finds a number's end with it.  No
** bound is checked: the bytes must be followed by one that is not part of
** a number, as a token in a reader's window is (by a delimiter or the
** window's 0 sentinel).  Inlined into the fast path's loops, where its
** call and the stores into d would cost as much as the scan itself
** (make bench-pbrt). */
#if defined(__GNUC__)
static inline int scan_decimal(const char **at, decimal *d, int values) __attribute__((always_inline));
#endif
static inline int scan_decimal(const char **at, decimal *d, int values)
{
    /* Locals, written to d once: stores through d might alias the bytes
    ** (they are chars), which would keep the compiler from holding them
    ** in registers over the loops. */
    const char *c = *at, *i0, *i1, *f0 = NULL;
    uint64_t m = 0;   /* wraps past 19 digits, where it is not kept */
    int exp10 = 0, k = DEC_OK, sig, lz = 0, int_sig;
    d->negative = 0;
    d->plain = 1;
    if (*c == '-' || *c == '+') { d->negative = *c++ == '-'; d->plain = 0; }
    i0 = c;
    while (*c == '0') c++;   /* leading zeros */
    c = take_digits(i1 = c, &m, values);
    int_sig = sig = (int)(c - i1);
    if (*c == '.') {
        const char *s0;
        d->plain = 0;
        f0 = ++c;
        if (sig == 0) while (*c == '0') c++;   /* 0.000ddd: leading zeros still */
        lz = (int)(c - f0);
        c = take_digits(s0 = c, &m, values);
        sig += (int)(c - s0);
        exp10 = -(int)(c - f0);
    }
    if (c - i0 - (f0 != NULL) <= 0) k = DEC_NO_DIGITS;
    else if (sig > 18) {   /* the first 18 digits' place: the number's magnitude */
        d->m = 0;
        d->digits = 19;
        d->exp10 = (int_sig > 0 ? int_sig : -lz) - 18;
    } else {
        d->m = m;
        d->digits = sig;
        d->exp10 = exp10;
    }
    if (k == DEC_OK && (*c == 'e' || *c == 'E')) {
        int eneg = 0, e = 0;
        d->plain = 0;
        c++;
        if (*c == '-' || *c == '+') eneg = *c++ == '-';
        if (*c < '0' || *c > '9') k = DEC_BAD_EXPONENT;
        for (; *c >= '0' && *c <= '9'; c++) if (e < 100000) e = e * 10 + (*c - '0');
        d->exp10 += eneg ? -e : e;
    }
    *at = c;
    return k;
}

/* The float strtof gives for the n characters at s, scanned as d.  pbrt
** reads every number into a float, so we do too; transforms then run in
** double from those floats.  The fast path is Clinger's (1990): with at
** most 15 significant digits and a power of ten of at most 22, one double
** division or product is correctly rounded; rounding that double to float
** is then right unless it lies exactly between two floats (double
** rounding), which, like every other case, goes to strtof. */
static int decimal_float(const decimal *d, const char *s, size_t n, float *out)
{
    static const double tens[23] = {1e0,  1e1,  1e2,  1e3,  1e4,  1e5,  1e6,  1e7,
                                    1e8,  1e9,  1e10, 1e11, 1e12, 1e13, 1e14, 1e15,
                                    1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22};
    static const float ftens[11] = {1e0f, 1e1f, 1e2f, 1e3f, 1e4f, 1e5f, 1e6f, 1e7f, 1e8f, 1e9f, 1e10f};
    char copy[128];
#if defined(FLT_EVAL_METHOD) && FLT_EVAL_METHOD == 0
    if (d->digits <= 15 && d->m <= (1u << 24) && d->exp10 >= -10 && d->exp10 <= 10) {
        /* Clinger's path in float (as the OBJ reader's): m and 10^10 are
        ** exact floats, so one float division or product is correctly
        ** rounded, and cheaper than the double one. */
        float f = d->exp10 < 0 ? (float)d->m / ftens[-d->exp10] : (float)d->m * ftens[d->exp10];
        *out = d->negative ? -f : f;
        return NUM_OK;
    }
    if (d->digits <= 15 && d->exp10 >= -22 && d->exp10 <= 22) {
        double v = d->exp10 < 0 ? (double)d->m / tens[-d->exp10] : (double)d->m * tens[d->exp10];
        float f = (float)v;
        uint64_t bits;
        memcpy(&bits, &v, sizeof bits);
        /* A normal float's midpoint is a double whose 29 bits below the
        ** float's 23 are exactly 1 followed by 28 zeros. */
        if (d->m == 0 || (v > 1e-30 && v < 1e30 && (bits & 0x1FFFFFFFu) != 0x10000000u)) {
            *out = d->negative ? -f : f;
            return NUM_OK;
        }
    }
#else
    (void)tens;
    (void)ftens;
#endif
    if (n >= sizeof copy) return NUM_BAD;
    memcpy(copy, s, n);
    copy[n] = 0;
    *out = strtof(copy, NULL);
    return isfinite(*out) ? NUM_OK : NUM_NOT_FINITE;
}

/* Whether decimal_float will give NUM_OK, without converting (pass 1's
** check of P): below 10^38 the value rounds to a finite float; larger
** or longer numbers go the whole way (0: not settled here). */
static int decimal_surely_finite(const decimal *d, size_t n)
{
    return n < 128 && (d->digits < 18 ? d->digits : 18) + d->exp10 <= 38;
}

/* A vertex index as scan_index reads it (0: not one). */
static int decimal_index(const decimal *d, size_t n, uint32_t *out)
{
    if (!d->plain || n > 10 || d->m > 0xFFFFFFFFu) return 0;
    *out = (uint32_t)d->m;
    return 1;
}

/* A whole token as a float: NUM_OK, NUM_BAD (not a number) or
** NUM_NOT_FINITE (inf, nan, or beyond the float range). */
static int scan_float(const char *s, size_t n, float *out)
{
    const char *c = s, *end = s + n;
    decimal d;
    int k = scan_decimal(&c, &d, 1);
    if (k == DEC_NO_DIGITS) return (n >= 3 && (strchr("iInN", c[0]) != NULL)) ? NUM_NOT_FINITE : NUM_BAD;
    if (k != DEC_OK || c != end) return NUM_BAD;
    return decimal_float(&d, s, n, out);
}

/* A non-negative decimal integer below 2^32 (pbrt's indices are ints;
** a sign, point or exponent is an error). */
static int scan_index(const char *s, size_t n, uint32_t *out)
{
    const char *c = s;
    decimal d;
    return n > 0 && scan_decimal(&c, &d, 1) == DEC_OK && c == s + n && decimal_index(&d, n, out);
}

/* ===================================================================== */
/* Part II: the tokenizer                                                */
/* ===================================================================== */
/*
** pbrt's tokens: '[' and ']', strings in double quotes (backslash escapes;
** no newline inside), comments from '#' to the end of the line, and bare
** words (directives, numbers, true/false) ended by white space, a quote,
** a bracket or '#'.  The reader keeps a window of the file; a token is
** always whole in the window, and valid until the next call.
*/

enum { TOK_EOF, TOK_WORD, TOK_STRING, TOK_OPEN, TOK_CLOSE };

typedef struct token {
    int kind;
    const char *s;      /* a string's text without its quotes (escapes kept) */
    size_t n;
    uint64_t offset;    /* of the token's first byte in its file */
    uint64_t line;
    uint32_t file;      /* index into the scene's file table */
} token;

typedef struct reader {
    int fd;
    uint32_t file;
    const char *name;       /* for messages */
    char *buf;              /* cap + 1 bytes: buf[end] is 0, a sentinel that ends
                            ** every number scan (scan_decimal) */
    size_t cap, pos, end;   /* unread bytes: buf[pos .. end) */
    uint64_t base;          /* file offset of buf[0]; the fd stands at base + end */
    uint64_t line;
    int eof;
    dev_t dev;              /* to find Include cycles */
    ino_t ino;
} reader;

static brt_result reader_open(reader *r, const char *path, uint32_t file, size_t cap,
                              brt_error *err)
{
    struct stat st;
    memset(r, 0, sizeof *r);
    r->fd = open(path, O_RDONLY);
    if (r->fd < 0) {
        int e = errno;   /* kept for the caller's message */
        brt_fail(err, BRT_EIO, "%s: %s", path, strerror(e));
        errno = e;
        return BRT_EIO;
    }
    if (fstat(r->fd, &st) != 0 || S_ISDIR(st.st_mode)) {
        close(r->fd);
        r->fd = -1;
        brt_fail(err, BRT_EIO, "%s: not a readable file", path);
        errno = EISDIR;
        return BRT_EIO;
    }
    r->dev = st.st_dev;
    r->ino = st.st_ino;
    r->buf = malloc(cap + 1);   /* + the sentinel */
    if (!r->buf) { close(r->fd); r->fd = -1; return brt_fail(err, BRT_ENOMEM, "out of memory"); }
    r->buf[0] = 0;
    r->cap = cap;
    r->file = file;
    r->name = path;
    r->line = 1;
    return BRT_OK;
}

static void reader_close(reader *r)
{
    if (r->fd >= 0) close(r->fd);
    free(r->buf);
    r->fd = -1;
    r->buf = NULL;
}

/* Moves the unread bytes to the front and reads more behind them.
** Returns 0, or -1 with errno. */
static int reader_fill(reader *r)
{
    if (r->pos > 0) {
        memmove(r->buf, r->buf + r->pos, r->end - r->pos);
        r->base += r->pos;
        r->end -= r->pos;
        r->pos = 0;
        r->buf[r->end] = 0;
    }
    while (r->end < r->cap && !r->eof) {
        ssize_t got = read(r->fd, r->buf + r->end, r->cap - r->end);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0) return -1;
        if (got == 0) r->eof = 1;
        r->end += (size_t)got;
        r->buf[r->end] = 0;
        if (r->end - r->pos >= MAX_TOKEN) break;   /* enough for a token: stay fast */
    }
    return 0;
}

/* Positions the reader at offset of its file (line: that offset's line),
** reusing the window when it holds the offset. */
static int reader_seek(reader *r, uint64_t offset, uint64_t line)
{
    r->line = line;
    if (offset >= r->base && offset <= r->base + r->end) {
        r->pos = (size_t)(offset - r->base);
        return 0;
    }
    if (lseek(r->fd, (off_t)offset, SEEK_SET) == (off_t)-1) return -1;
    r->base = offset;
    r->pos = r->end = 0;
    r->buf[0] = 0;
    r->eof = 0;
    return 0;
}

/* Characters that end a bare word: white space, a quote, a bracket, '#'.
** A table, because the tokenizer asks for every byte of the numbers. */
static const unsigned char delimiter[256] = {
    ['\t'] = 1, ['\n'] = 1, ['\v'] = 1, ['\f'] = 1, ['\r'] = 1, [' '] = 1,
    ['"'] = 1, ['#'] = 1, ['['] = 1, [']'] = 1};

/* The blanks number_at skips (\f and \v are next_token's). */
static const unsigned char blank[256] = {['\t'] = 1, ['\n'] = 1, ['\r'] = 1, [' '] = 1};

/* Skips white space and comments; 1 when a token starts at pos, 0 at the
** end of the file, -1 on a read error. */
static int skip_blank(reader *r)
{
    for (;;) {
        char c;
        if (r->pos == r->end) {
            if (r->eof) return 0;
            if (reader_fill(r) != 0) return -1;
            continue;
        }
        c = r->buf[r->pos];
        if (c == '\n') { r->line++; r->pos++; }
        else if (c == ' ' || c == '\t' || c == '\r' || c == '\f' || c == '\v') r->pos++;
        else if (c == '#') {
            for (;;) {
                char *nl = memchr(r->buf + r->pos, '\n', r->end - r->pos);
                if (nl) { r->pos = (size_t)(nl - r->buf); break; }
                r->pos = r->end;
                if (r->eof) return 0;
                if (reader_fill(r) != 0) return -1;
            }
        } else return 1;
    }
}

/* The length of the token at pos when it ends inside the window (0 when
** it may go on past the window's end, -1 for a string broken by a
** newline or the end of the file). */
static long token_length(const reader *r)
{
    const char *s = r->buf + r->pos, *e = r->buf + r->end;
    const char *c = s + 1;
    if (*s == '[' || *s == ']') return 1;
    if (*s == '"') {
        for (; c < e; c++) {
            if (*c == '\\') { c++; continue; }
            if (*c == '"') return (long)(c + 1 - s);
            if (*c == '\n') return -1;
        }
        return r->eof ? -1 : 0;
    }
    while (c < e && !delimiter[(unsigned char)*c]) c++;
    return (c < e || r->eof) ? (long)(c - s) : 0;
}

/* The next token (TOK_EOF at the end of the file). */
static brt_result next_token(reader *r, token *t, brt_error *err)
{
    long len;
    int k = skip_blank(r);
    if (k < 0) return brt_fail(err, BRT_EIO, "%s:%llu: %s", r->name, (unsigned long long)r->line, strerror(errno));
    t->line = r->line;
    t->file = r->file;
    if (k == 0) { t->kind = TOK_EOF; t->s = ""; t->n = 0; t->offset = r->base + r->pos; return BRT_OK; }
    while ((len = token_length(r)) == 0) {
        if (r->end - r->pos >= MAX_TOKEN)
            return brt_fail(err, BRT_EPARSE, "%s:%llu: token longer than %lu bytes", r->name,
                            (unsigned long long)r->line, (unsigned long)MAX_TOKEN);
        if (reader_fill(r) != 0)
            return brt_fail(err, BRT_EIO, "%s:%llu: %s", r->name, (unsigned long long)r->line, strerror(errno));
    }
    if (len < 0) return brt_fail(err, BRT_EPARSE, "%s:%llu: unterminated string", r->name, (unsigned long long)r->line);
    t->offset = r->base + r->pos;
    t->s = r->buf + r->pos;
    t->n = (size_t)len;
    r->pos += (size_t)len;
    switch (*t->s) {
    case '[': t->kind = TOK_OPEN; break;
    case ']': t->kind = TOK_CLOSE; break;
    case '"': t->kind = TOK_STRING; t->s++; t->n -= 2; break;
    default: t->kind = TOK_WORD;
    }
    return BRT_OK;
}

/* Control characters of text (a name may hold "\n" escapes) become '?',
** so that a message or the summary stays one line. */
static void printable(char *text)
{
    for (; *text; text++)
        if ((unsigned char)*text < 32 || *text == 127) *text = '?';
}

/* The fast path of the number lists (a mesh's P and indices, nearly all
** of a big file's bytes).  From *at in a window ending at e (its sentinel
** behind): skips blanks (not comments), counting newlines in *line, and
** when a number lies whole in the window and a delimiter ends it, scans
** it into d and returns its length, *at at its first byte; 0 when the
** next token is for next_token (a comment, ']', the window's end, a word
** that is not a number), *at there.  One scan of the bytes finds the
** number's end and its value, where next_token and scan_float would scan
** them twice; the callers keep *at and *line in registers over a list. */
#if defined(__GNUC__)
static inline size_t number_at(const char **at, const char *e, uint64_t *line, decimal *d, int values)
    __attribute__((always_inline));
#endif
static inline size_t number_at(const char **at, const char *e, uint64_t *line, decimal *d, int values)
{
    const char *c = *at, *s;
    if (*c == ' ') c++;   /* the usual one blank, then the rest */
    for (; blank[(unsigned char)*c]; c++) *line += *c == '\n';   /* the sentinel is no blank */
    *at = s = c;
    if (scan_decimal(&c, d, values) != DEC_OK || c == e || !delimiter[(unsigned char)*c]) return 0;
    return (size_t)(c - s);
}

/* A string token's text with escapes resolved, into out (size bytes);
** 0 when it does not fit. */
static int unescape(const token *t, char *out, size_t size)
{
    size_t i, o = 0;
    for (i = 0; i < t->n; i++) {
        char c = t->s[i];
        if (c == '\\' && i + 1 < t->n) {
            c = t->s[++i];
            c = c == 'n' ? '\n' : c == 't' ? '\t' : c == 'r' ? '\r' : c == 'b' ? '\b' : c == 'f' ? '\f' : c;
        }
        if (o + 1 >= size) return 0;
        out[o++] = c;
    }
    out[o] = 0;
    return 1;
}

/* ===================================================================== */
/* Part III: affine transforms in double                                  */
/* ===================================================================== */
/*
** A transform is a row-major 3x4 matrix [M | d] (brt_instance's layout):
** p' = M p + d; the implied last row is 0 0 0 1.
*/

static void xf_identity(double m[12])
{
    memset(m, 0, 12 * sizeof *m);
    m[0] = m[5] = m[10] = 1;
}

/* out = a * b (b acts first); out may be a or b. */
static void xf_mul(const double a[12], const double b[12], double out[12])
{
    double r[12];
    int i, j;
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 4; j++)
            r[4 * i + j] = a[4 * i] * b[j] + a[4 * i + 1] * b[4 + j] + a[4 * i + 2] * b[8 + j];
        r[4 * i + 3] += a[4 * i + 3];
    }
    memcpy(out, r, sizeof r);
}

static double xf_det(const double m[12])
{
    return m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8])
         + m[2] * (m[4] * m[9] - m[5] * m[8]);
}

static int xf_finite(const double m[12])
{
    int i;
    for (i = 0; i < 12; i++) if (!isfinite(m[i])) return 0;
    return 1;
}

/* The inverse by cofactors; 0 when singular or not finite. */
static int xf_invert(const double m[12], double out[12])
{
    double det = xf_det(m), c[9];
    int i;
    if (det == 0 || !isfinite(det)) return 0;
    c[0] = m[5] * m[10] - m[6] * m[9];  c[1] = m[2] * m[9] - m[1] * m[10]; c[2] = m[1] * m[6] - m[2] * m[5];
    c[3] = m[6] * m[8] - m[4] * m[10];  c[4] = m[0] * m[10] - m[2] * m[8]; c[5] = m[2] * m[4] - m[0] * m[6];
    c[6] = m[4] * m[9] - m[5] * m[8];   c[7] = m[1] * m[8] - m[0] * m[9];  c[8] = m[0] * m[5] - m[1] * m[4];
    for (i = 0; i < 3; i++) {
        out[4 * i] = c[3 * i] / det;
        out[4 * i + 1] = c[3 * i + 1] / det;
        out[4 * i + 2] = c[3 * i + 2] / det;
        out[4 * i + 3] = -(out[4 * i] * m[3] + out[4 * i + 1] * m[7] + out[4 * i + 2] * m[11]);
    }
    return xf_finite(out);
}

/* A float point through m, in double, rounded once.  Terms whose
** coefficient is 0 are left out rather than added as +0: the identity
** then gives back every float bit for bit, -0 included (as the OBJ
** reader reads the same text); other sums are unchanged. */
static void xf_point(const double m[12], const float p[3], float out[3])
{
    double v[4];
    int i, j;
    v[0] = p[0]; v[1] = p[1]; v[2] = p[2]; v[3] = 1;
    for (i = 0; i < 3; i++) {
        double acc = 0;
        int any = 0;
        for (j = 0; j < 4; j++) {
            if (m[4 * i + j] == 0) continue;
            acc = any ? acc + m[4 * i + j] * v[j] : m[4 * i + j] * v[j];
            any = 1;
        }
        out[i] = (float)acc;
    }
}

/* pbrt's Rotate(theta, axis): about the unit axis, right-handed. */
static int xf_rotate(double degrees, double ax, double ay, double az, double m[12])
{
    double len = sqrt(ax * ax + ay * ay + az * az), s, c;
    if (!(len > 0) || !isfinite(len)) return 0;
    ax /= len; ay /= len; az /= len;
    s = sin(degrees * (PI / 180));
    c = cos(degrees * (PI / 180));
    m[0] = ax * ax + (1 - ax * ax) * c; m[1] = ax * ay * (1 - c) - az * s; m[2] = ax * az * (1 - c) + ay * s;
    m[4] = ax * ay * (1 - c) + az * s;  m[5] = ay * ay + (1 - ay * ay) * c; m[6] = ay * az * (1 - c) - ax * s;
    m[8] = ax * az * (1 - c) - ay * s;  m[9] = ay * az * (1 - c) + ax * s;  m[10] = az * az + (1 - az * az) * c;
    m[3] = m[7] = m[11] = 0;
    return 1;
}

static void normalize(double v[3])
{
    double len = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    if (len > 0) { v[0] /= len; v[1] /= len; v[2] /= len; }
}

/* pbrt's LookAt: camera-from-world for an eye at e looking at l, up u
** (worldFromCamera has columns right = up x dir, newUp = dir x right,
** dir, e).  0 when up is parallel to the view direction or zero. */
static int xf_look_at(const double v[9], double m[12])
{
    double dir[3], up[3], right[3], nup[3], w[12];
    int k;
    for (k = 0; k < 3; k++) { dir[k] = v[3 + k] - v[k]; up[k] = v[6 + k]; }
    normalize(dir);
    normalize(up);
    right[0] = up[1] * dir[2] - up[2] * dir[1];
    right[1] = up[2] * dir[0] - up[0] * dir[2];
    right[2] = up[0] * dir[1] - up[1] * dir[0];
    if (!(right[0] * right[0] + right[1] * right[1] + right[2] * right[2] > 0)) return 0;
    normalize(right);
    nup[0] = dir[1] * right[2] - dir[2] * right[1];
    nup[1] = dir[2] * right[0] - dir[0] * right[2];
    nup[2] = dir[0] * right[1] - dir[1] * right[0];
    for (k = 0; k < 3; k++) {
        w[4 * k] = right[k];
        w[4 * k + 1] = nup[k];
        w[4 * k + 2] = dir[k];
        w[4 * k + 3] = v[k];
    }
    return xf_invert(w, m);
}

/* ===================================================================== */
/* Part IV: pass 1, the structure                                        */
/* ===================================================================== */

enum { SHAPE_TRIANGLES, SHAPE_BILINEAR, SHAPE_PLY, SHAPE_LOOP };

/* A triangle shape: where its numbers are and the transform baked in. */
typedef struct shape {
    double xform[12];       /* the CTM at the shape: its object (or world) space */
    uint64_t p_offset, i_offset;   /* of P's and indices' values ('[' or the number) */
    uint64_t p_line, i_line;
    uint64_t p_count, i_count;     /* numbers in them; i_count 0: no indices */
    uint32_t p_file, i_file;       /* file table indices (plymesh: p_file is its path) */
    uint32_t object;        /* NO_OBJECT for a world shape */
    int has_indices;        /* 0: the implicit one triangle or patch */
    uint32_t line;          /* of the Shape directive */
    uint32_t file;
    int kind;
    int identity;           /* xform is the identity: points pass unchanged */
    int levels;             /* loopsubdiv: its "levels" */
} shape;

/* An object name: defined by ObjectBegin, used by ObjectInstance. */
typedef struct object {
    char *name;
    int defined;
    uint32_t prototype;     /* its number, in ObjectBegin order */
    uint32_t first_shape, shape_count;
    uint32_t use_file, use_line;   /* the first ObjectInstance, for messages */
} object;

typedef struct named_xf { char *name; double m[12]; } named_xf;
typedef struct skip_count { char key[96]; uint64_t count; } skip_count;

struct ex_pbrt {
    char **files;           /* paths: scene files and PLY files */
    uint32_t file_count;
    size_t file_cap;
    char *folder;           /* of the main file, for relative paths */
    shape *shapes;
    size_t shape_count, shape_cap;
    uint64_t world_shapes;
    object *objects;        /* by slot (first mention) */
    uint32_t object_count;
    size_t object_cap;
    uint32_t *slot_of;      /* hash table: slot + 1, 0 empty */
    size_t hash_cap;
    uint32_t *prototypes;   /* prototype number -> slot */
    uint32_t prototype_count;
    size_t prototype_cap;
    brt_instance *instances;
    size_t instance_count, instance_cap;
    skip_count *skipped;
    size_t skip_count, skip_cap;
    char *summary;
    int has_camera, mirrored;
    float eye[3], target[3], up[3], fov;
    double world_from_camera[12];   /* the inverse of the CTM at Camera */
    double screen[4];       /* screenwindow x0 x1 y0 y1, when has_screen */
    double frame;           /* frameaspectratio; 0: the image's */
    int has_screen;
    uint32_t film_width, film_height;
    int has_film;
};

/* The graphics state pbrt pushes at AttributeBegin and ObjectBegin. */
typedef struct gstate {
    double ctm[12];
    int start_active;       /* ActiveTransform: does the start time change? */
    char kind;              /* what pushed it: 'a' AttributeBegin, 't' TransformBegin,
                            ** 'o' ObjectBegin */
    uint32_t file, line;    /* where */
} gstate;

/* Per open file: an Import's graphics state to restore at its end, and
** the stack depth its blocks start at (AttributeEnd may not go below it). */
typedef struct file_frame {
    int import;
    gstate g;
    size_t base;
} file_frame;

typedef struct parser {
    ex_pbrt *scene;
    reader files[MAX_DEPTH];
    file_frame frames[MAX_DEPTH];
    int depth;
    token peek;
    int peeked;
    gstate g;
    gstate *stack;
    size_t stack_count, stack_cap;
    uint32_t object;        /* slot being defined, or NO_OBJECT */
    named_xf *named;
    size_t named_count, named_cap;
    brt_error *err;
} parser;

#define GROW(p, arr, count, cap) \
    ((count) < (cap) ? 0 : grow_array((void **)&(arr), &(cap), (count) + 1, sizeof *(arr), (p)->err))

static int grow_array(void **arr, size_t *cap, size_t need, size_t size, brt_error *err)
{
    void *bigger = brt_grow(*arr, cap, need, size);
    if (!bigger) { brt_fail(err, BRT_ENOMEM, "out of memory"); return -1; }
    *arr = bigger;
    return 0;
}

/* "file:line: message" at a token. */
static brt_result fail_at(parser *p, const token *t, brt_result r, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 4, 5)))
#endif
    ;
static brt_result fail_at(parser *p, const token *t, brt_result r, const char *fmt, ...)
{
    char text[400];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(text, sizeof text, fmt, ap);
    va_end(ap);
    return brt_fail(p->err, r, "%s:%llu: %s", p->scene->files[t->file], (unsigned long long)t->line, text);
}

/* The directive that opens a block of kind 'a', 't' or 'o'. */
static const char *block_begin(char kind)
{
    return kind == 'a' ? "AttributeBegin" : kind == 't' ? "TransformBegin" : "ObjectBegin";
}

static brt_result never_closed(parser *p, const gstate *top)
{
    return brt_fail(p->err, BRT_EPARSE, "%s:%lu: %s never closed", p->scene->files[top->file],
                    (unsigned long)top->line, block_begin(top->kind));
}

/* The next token of the file tree: the end of an included file returns
** to the file that included it (an Include is textual).  The end of an
** imported file is a TOK_EOF, left for parse (end_import): no directive
** goes on past it into the importing file. */
static brt_result next(parser *p, token *t)
{
    brt_result r;
    if (p->peeked) { *t = p->peek; p->peeked = 0; return BRT_OK; }
    for (;;) {
        r = next_token(&p->files[p->depth - 1], t, p->err);
        if (r != BRT_OK || t->kind != TOK_EOF || p->depth == 1 || p->frames[p->depth - 1].import) return r;
        reader_close(&p->files[--p->depth]);
    }
}

/* The end of an imported file restores the graphics state of its Import:
** pbrt-v4 parses an Import with a copy of the builder (scene.cpp
** CopyForImport) and merges back only what it defined (MergeImported), so
** its transforms and ActiveTransform do not reach the importing file; a
** block it opened and did not close is an error there too. */
static brt_result end_import(parser *p)
{
    const file_frame *f = &p->frames[p->depth - 1];
    if (p->stack_count > f->base) return never_closed(p, &p->stack[p->stack_count - 1]);
    p->g = f->g;
    reader_close(&p->files[--p->depth]);
    return BRT_OK;
}

static void unget(parser *p, const token *t)
{
    p->peek = *t;
    p->peeked = 1;
}

static int token_is(const token *t, const char *word)
{
    size_t n = strlen(word);
    return t->n == n && memcmp(t->s, word, n) == 0;
}

/* A short printable form of a token for messages. */
static const char *shown(const token *t, char *buf, size_t size)
{
    size_t n = t->n < size - 4 ? t->n : size - 4, i;
    if (t->kind == TOK_EOF) return "end of file";
    for (i = 0; i < n; i++) buf[i] = (t->s[i] >= 32 && t->s[i] < 127) ? t->s[i] : '?';
    strcpy(buf + n, t->n > n ? "..." : "");
    return buf;
}

static brt_result expect_number(parser *p, double *value)
{
    token t;
    float f;
    char b[40];
    int k;
    brt_result r = next(p, &t);
    if (r != BRT_OK) return r;
    if (t.kind != TOK_WORD || (k = scan_float(t.s, t.n, &f)) == NUM_BAD)
        return fail_at(p, &t, BRT_EPARSE, "expected a number, got '%s'", shown(&t, b, sizeof b));
    if (k == NUM_NOT_FINITE) return fail_at(p, &t, BRT_EPARSE, "non-finite number '%s'", shown(&t, b, sizeof b));
    *value = f;
    return BRT_OK;
}

static brt_result expect_numbers(parser *p, double *v, int n)
{
    int i;
    for (i = 0; i < n; i++) {
        brt_result r = expect_number(p, &v[i]);
        if (r != BRT_OK) return r;
    }
    return BRT_OK;
}

/* A quoted string argument, unescaped into out. */
static brt_result expect_string(parser *p, const char *what, char *out, size_t size, token *where)
{
    char b[40];
    brt_result r = next(p, where);
    if (r != BRT_OK) return r;
    if (where->kind != TOK_STRING)
        return fail_at(p, where, BRT_EPARSE, "%s: expected a quoted string, got '%s'", what, shown(where, b, sizeof b));
    if (!unescape(where, out, size)) return fail_at(p, where, BRT_EPARSE, "%s: string too long", what);
    return BRT_OK;
}

/* Counts a skipped directive under key for the summary. */
static brt_result count_skipped(parser *p, const char *key)
{
    ex_pbrt *s = p->scene;
    size_t i;
    for (i = 0; i < s->skip_count; i++)
        if (strcmp(s->skipped[i].key, key) == 0) { s->skipped[i].count++; return BRT_OK; }
    if (GROW(p, s->skipped, s->skip_count, s->skip_cap)) return BRT_ENOMEM;
    snprintf(s->skipped[s->skip_count].key, sizeof s->skipped->key, "%s", key);
    printable(s->skipped[s->skip_count].key);
    s->skipped[s->skip_count++].count = 1;
    return BRT_OK;
}

/* Adds a path to the file table (messages and the streams name files by
** their index); returns the index or -1. */
static long add_file(parser *p, const char *path)
{
    ex_pbrt *s = p->scene;
    char *copy = malloc(strlen(path) + 1);
    if (!copy || GROW(p, s->files, s->file_count, s->file_cap)) {
        free(copy);
        brt_fail(p->err, BRT_ENOMEM, "out of memory");
        return -1;
    }
    strcpy(copy, path);
    s->files[s->file_count] = copy;
    return (long)s->file_count++;
}

/* A file name of the scene resolved as pbrt does: against the folder of
** the main file unless absolute. */
static int resolve(const parser *p, const char *name, char *out, size_t size)
{
    int n = name[0] == '/' || p->scene->folder[0] == 0
        ? snprintf(out, size, "%s", name)
        : snprintf(out, size, "%s/%s", p->scene->folder, name);
    return n >= 0 && (size_t)n < size;
}

/* Starts reading an included (import: imported) file; where is the
** directive's token. */
static brt_result push_file(parser *p, const char *path, const token *where, int import)
{
    reader *r;
    long file;
    int i;
    brt_result res;
    if (p->depth == MAX_DEPTH)
        return fail_at(p, where, BRT_EPARSE, "Includes nested more than %d deep", MAX_DEPTH);
    file = add_file(p, path);
    if (file < 0) return BRT_ENOMEM;
    r = &p->files[p->depth];
    res = reader_open(r, p->scene->files[file], (uint32_t)file, PASS1_WINDOW, p->err);
    if (res != BRT_OK) {
        return fail_at(p, where, res, "cannot read included file \"%s\": %s", path,
                       res == BRT_EIO ? strerror(errno) : "out of memory");
    }
    for (i = 0; i < p->depth; i++)
        if (p->files[i].dev == r->dev && p->files[i].ino == r->ino) {
            reader_close(r);
            return fail_at(p, where, BRT_EPARSE, "Include cycle: \"%s\" is already being read", path);
        }
    p->frames[p->depth].import = import;
    p->frames[p->depth].g = p->g;
    p->frames[p->depth].base = import ? p->stack_count : p->frames[p->depth - 1].base;
    p->depth++;
    return BRT_OK;
}

/* ---- Parameter lists ---------------------------------------------- */

/* What a directive wants from its parameter list (the rest is skipped). */
typedef struct wanted {
    int shape_kind;         /* -1: not a triangle shape */
    int camera, film;
    const char *report;     /* a directive that is read (its name): the
                            ** parameters it does not use are counted as skipped */
    /* found */
    int has_p, has_i, has_filename;
    uint64_t p_offset, i_offset, p_line, i_line, p_count, i_count;
    uint32_t p_file, i_file;
    uint32_t i_max;
    token i_token;          /* the largest index's token, for messages */
    double fov;
    double screen[4], frame;   /* Camera: screenwindow, frameaspectratio */
    int screen_n, has_frame;
    token screen_at;
    uint32_t xres, yres;    /* Film */
    int alpha;              /* Shape: ALPHA_* */
    int levels;             /* loopsubdiv */
    char filename[4096];
} wanted;

/* A shape's "alpha": pbrt-v4 never reports a hit where it is 0, and one
** below 1 lets a hit through at random (a hash of the ray), which a
** deterministic first hit cannot keep. */
enum { ALPHA_ONE, ALPHA_ZERO, ALPHA_PARTIAL, ALPHA_TEXTURE };

static int known_type(const char *type)
{
    static const char *const types[] = {
        "integer", "float", "point2", "vector2", "point3", "vector3", "normal3", "normal",
        "point", "vector", "color", "rgb", "spectrum", "blackbody", "string", "texture", "bool"};
    size_t i;
    for (i = 0; i < sizeof types / sizeof *types; i++)
        if (strcmp(type, types[i]) == 0) return 1;
    return 0;
}

/* Reads a value: '[' values ']' or one value.  For each value token calls
** fn (NULL: skip it).  *first: the first token (the '[' or the value). */
typedef brt_result (*value_fn)(parser *p, const token *t, wanted *w);

static brt_result value_point(parser *p, const token *t, wanted *w);
static brt_result value_index(parser *p, const token *t, wanted *w);
static void take_numbers(parser *p, value_fn fn, wanted *w);

static brt_result read_value(parser *p, const char *name, value_fn fn, wanted *w, token *first)
{
    token t;
    char b[40];
    brt_result r = next(p, first);
    if (r != BRT_OK) return r;
    if (first->kind == TOK_WORD || first->kind == TOK_STRING) return fn ? fn(p, first, w) : BRT_OK;
    if (first->kind != TOK_OPEN)
        return fail_at(p, first, BRT_EPARSE, "parameter \"%s\": expected a value, got '%s'", name,
                       shown(first, b, sizeof b));
    for (;;) {
        if (fn == value_point || fn == value_index) take_numbers(p, fn, w);
        if ((r = next(p, &t)) != BRT_OK) return r;
        if (t.kind == TOK_CLOSE) return BRT_OK;
        if (t.kind != TOK_WORD && t.kind != TOK_STRING)
            return fail_at(p, &t, BRT_EPARSE, "parameter \"%s\": expected a value or ']', got '%s'", name,
                           shown(&t, b, sizeof b));
        if (fn && (r = fn(p, &t, w)) != BRT_OK) return r;
    }
}

static brt_result value_point(parser *p, const token *t, wanted *w)
{
    float f;
    char b[40];
    int k = t->kind == TOK_WORD ? scan_float(t->s, t->n, &f) : NUM_BAD;
    if (k == NUM_BAD) return fail_at(p, t, BRT_EPARSE, "\"P\": expected a number, got '%s'", shown(t, b, sizeof b));
    if (k == NUM_NOT_FINITE) return fail_at(p, t, BRT_EPARSE, "\"P\": non-finite number '%s'", shown(t, b, sizeof b));
    w->p_count++;
    return BRT_OK;
}

/* Counts an index; the largest one's place names it in messages. */
static void note_index(wanted *w, uint32_t v, uint32_t file, uint64_t line)
{
    if (w->i_count == 0 || v > w->i_max) {
        w->i_max = v;
        w->i_token.kind = TOK_WORD;
        w->i_token.s = "";
        w->i_token.n = 0;
        w->i_token.file = file;
        w->i_token.line = line;
    }
    w->i_count++;
}

static brt_result value_index(parser *p, const token *t, wanted *w)
{
    uint32_t v;
    char b[40];
    if (t->kind != TOK_WORD || !scan_index(t->s, t->n, &v))
        return fail_at(p, t, BRT_EPARSE, "\"indices\": expected a vertex index (0 .. 2^32-1), got '%s'",
                       shown(t, b, sizeof b));
    note_index(w, v, t->file, t->line);
    return BRT_OK;
}

/* The numbers of P or indices straight from the window (number_at),
** checked as value_point and value_index check them; stops at the first
** token those must see (a number not settled here: its error, if any,
** is theirs to report, with the same message). */
static void take_numbers(parser *p, value_fn fn, wanted *w)
{
    reader *r = &p->files[p->depth - 1];
    const char *c = r->buf + r->pos, *e = r->buf + r->end;
    uint64_t line = r->line, count = 0;
    decimal d;
    size_t n;
    uint32_t v;
    if (p->peeked) return;
    if (fn == value_point) {
        for (; (n = number_at(&c, e, &line, &d, 0)) != 0 && decimal_surely_finite(&d, n); c += n) count++;
        w->p_count += count;
    } else {
        for (; (n = number_at(&c, e, &line, &d, 1)) != 0 && decimal_index(&d, n, &v); c += n)
            note_index(w, v, r->file, line);
    }
    r->pos = (size_t)(c - r->buf);
    r->line = line;
}

static brt_result value_fov(parser *p, const token *t, wanted *w)
{
    float f;
    char b[40];
    if (t->kind != TOK_WORD || scan_float(t->s, t->n, &f) != NUM_OK || !(f > 0 && f < 180))
        return fail_at(p, t, BRT_EPARSE, "\"fov\": expected degrees in (0, 180), got '%s'", shown(t, b, sizeof b));
    w->fov = f;
    return BRT_OK;
}

/* A positive finite number, for the parameters below. */
static brt_result positive(parser *p, const token *t, const char *name, double *out)
{
    float f;
    char b[40];
    if (t->kind != TOK_WORD || scan_float(t->s, t->n, &f) != NUM_OK || !(f > 0))
        return fail_at(p, t, BRT_EPARSE, "\"%s\": expected a positive number, got '%s'", name, shown(t, b, sizeof b));
    *out = f;
    return BRT_OK;
}

static brt_result value_frame(parser *p, const token *t, wanted *w)
{
    w->has_frame = 1;
    return positive(p, t, "frameaspectratio", &w->frame);
}

/* screenwindow: four numbers, x0 x1 y0 y1 (counted; do_camera checks 4). */
static brt_result value_screen(parser *p, const token *t, wanted *w)
{
    float f;
    char b[40];
    if (t->kind != TOK_WORD || scan_float(t->s, t->n, &f) != NUM_OK)
        return fail_at(p, t, BRT_EPARSE, "\"screenwindow\": expected a number, got '%s'", shown(t, b, sizeof b));
    if (w->screen_n == 0) w->screen_at = *t;
    if (w->screen_n < 4) w->screen[w->screen_n] = f;
    w->screen_n++;
    return BRT_OK;
}

/* Film's xresolution and yresolution: whole pixels, at least 1. */
static brt_result value_resolution(parser *p, const token *t, wanted *w, uint32_t *out, const char *name)
{
    uint32_t v;
    char b[40];
    if (t->kind != TOK_WORD || !scan_index(t->s, t->n, &v) || v < 1 || v > 0x7FFFFFFFu)
        return fail_at(p, t, BRT_EPARSE, "\"%s\": expected a number of pixels, got '%s'", name, shown(t, b, sizeof b));
    (void)w;
    *out = v;
    return BRT_OK;
}

static brt_result value_xres(parser *p, const token *t, wanted *w)
{
    return value_resolution(p, t, w, &w->xres, "xresolution");
}

static brt_result value_yres(parser *p, const token *t, wanted *w)
{
    return value_resolution(p, t, w, &w->yres, "yresolution");
}

static brt_result value_alpha(parser *p, const token *t, wanted *w)
{
    float f;
    char b[40];
    if (t->kind != TOK_WORD || scan_float(t->s, t->n, &f) != NUM_OK)
        return fail_at(p, t, BRT_EPARSE, "\"alpha\": expected a number, got '%s'", shown(t, b, sizeof b));
    /* pbrt-v4 (scene.cpp) makes no alpha test for 1 or more; a hit is
    ** dropped where the value is 0 or less. */
    w->alpha = f >= 1 ? ALPHA_ONE : f <= 0 ? ALPHA_ZERO : ALPHA_PARTIAL;
    return BRT_OK;
}

static brt_result value_alpha_texture(parser *p, const token *t, wanted *w)
{
    (void)p; (void)t;
    w->alpha = ALPHA_TEXTURE;
    return BRT_OK;
}

/* loopsubdiv's "integer levels": any int (pbrt-v4 refines none for 0 or
** less). */
static brt_result value_levels(parser *p, const token *t, wanted *w)
{
    char text[40], *end;
    long v;
    char b[40];
    if (t->kind != TOK_WORD || t->n >= sizeof text)
        return fail_at(p, t, BRT_EPARSE, "\"levels\": expected an integer, got '%s'", shown(t, b, sizeof b));
    memcpy(text, t->s, t->n);
    text[t->n] = 0;
    errno = 0;
    v = strtol(text, &end, 10);
    if (end == text || *end || errno || v < INT_MIN || v > INT_MAX)
        return fail_at(p, t, BRT_EPARSE, "\"levels\": expected an integer, got '%s'", shown(t, b, sizeof b));
    w->levels = (int)v;
    return BRT_OK;
}

/* loopsubdiv's "string scheme": pbrt-v4 reads it and uses Loop's scheme
** whatever it says, so it is neither used nor reported here. */
static brt_result value_ignored(parser *p, const token *t, wanted *w)
{
    (void)p; (void)t; (void)w;
    return BRT_OK;
}

static brt_result value_filename(parser *p, const token *t, wanted *w)
{
    if (t->kind != TOK_STRING || !unescape(t, w->filename, sizeof w->filename))
        return fail_at(p, t, BRT_EPARSE, "\"filename\": expected a file name");
    w->has_filename = 1;
    return BRT_OK;
}

/* The value reader of a parameter the directive uses, or NULL to skip. */
static value_fn wanted_fn(wanted *w, const char *type, const char *name)
{
    int points = strcmp(type, "point3") == 0 || strcmp(type, "point") == 0;
    int real = strcmp(type, "float") == 0, whole = strcmp(type, "integer") == 0;
    if (w->camera) {
        if (real && strcmp(name, "fov") == 0) return value_fov;
        if (real && strcmp(name, "screenwindow") == 0) return value_screen;
        if (real && strcmp(name, "frameaspectratio") == 0) return value_frame;
        return NULL;
    }
    if (w->film) {
        if (whole && strcmp(name, "xresolution") == 0) return value_xres;
        if (whole && strcmp(name, "yresolution") == 0) return value_yres;
        return NULL;
    }
    if (w->shape_kind >= 0 && strcmp(name, "alpha") == 0)
        return real ? value_alpha : strcmp(type, "texture") == 0 ? value_alpha_texture : NULL;
    if (w->shape_kind == SHAPE_PLY)
        return strcmp(type, "string") == 0 && strcmp(name, "filename") == 0 ? value_filename : NULL;
    if (w->shape_kind < 0) return NULL;
    if (w->shape_kind == SHAPE_LOOP && whole && strcmp(name, "levels") == 0) return value_levels;
    if (w->shape_kind == SHAPE_LOOP && strcmp(type, "string") == 0 && strcmp(name, "scheme") == 0)
        return value_ignored;
    if (points && strcmp(name, "P") == 0) return value_point;
    if (strcmp(type, "integer") == 0 && strcmp(name, "indices") == 0) return value_index;
    return NULL;
}

/* A parameter list: "type name" value, ... up to the first token that is
** not a string (left for the next directive). */
static brt_result read_params(parser *p, wanted *w)
{
    for (;;) {
        token t, first;
        char decl[256], type[64], name[192], extra[2];
        value_fn fn;
        brt_result r = next(p, &t);
        if (r != BRT_OK) return r;
        if (t.kind != TOK_STRING) { unget(p, &t); return BRT_OK; }
        if (!unescape(&t, decl, sizeof decl) || sscanf(decl, "%63s %191s %1s", type, name, extra) != 2)
            return fail_at(p, &t, BRT_EPARSE, "bad parameter declaration \"%.60s\" (expected \"type name\")", decl);
        if (!known_type(type)) return fail_at(p, &t, BRT_EPARSE, "unknown parameter type \"%s\"", type);
        fn = wanted_fn(w, type, name);
        if (fn == value_point) w->p_count = 0;      /* a repeated parameter: the last counts */
        if (fn == value_index) w->i_count = 0;
        if (fn == value_screen) w->screen_n = 0;
        if ((r = read_value(p, name, fn, w, &first)) != BRT_OK) return r;
        if (!fn && w->report) {   /* uv, N, S, lensradius, a Film's filename, ... */
            char key[220];
            snprintf(key, sizeof key, "%s parameter \"%s\"", w->report, name);
            if ((r = count_skipped(p, key)) != BRT_OK) return r;
        }
        if (fn == value_point) {
            w->has_p = 1; w->p_offset = first.offset; w->p_line = first.line; w->p_file = first.file;
        } else if (fn == value_index) {
            w->has_i = 1; w->i_offset = first.offset; w->i_line = first.line; w->i_file = first.file;
        }
    }
}

/* ---- Directives ---------------------------------------------------- */

/* The CTM changes only at the start time (see the header). */
static void apply(parser *p, const double m[12])
{
    if (p->g.start_active) xf_mul(p->g.ctm, m, p->g.ctm);
}

static brt_result check_ctm(parser *p, const token *at, const char *what)
{
    if (!xf_finite(p->g.ctm)) return fail_at(p, at, BRT_EPARSE, "%s: the transform is not finite", what);
    if (xf_det(p->g.ctm) == 0) return fail_at(p, at, BRT_EPARSE, "%s: singular transform (determinant 0)", what);
    return BRT_OK;
}

static brt_result do_transform(parser *p, const token *d, int concat)
{
    double v[16], m[12];
    token t;
    int bracket, i;
    brt_result r = next(p, &t);
    if (r != BRT_OK) return r;
    bracket = t.kind == TOK_OPEN;
    if (!bracket) unget(p, &t);
    if ((r = expect_numbers(p, v, 16)) != BRT_OK) return r;
    if (bracket) {
        if ((r = next(p, &t)) != BRT_OK) return r;
        if (t.kind != TOK_CLOSE) return fail_at(p, &t, BRT_EPARSE, "expected ']' after 16 numbers");
    }
    /* Column by column: row i of the matrix is v[i], v[4+i], v[8+i], v[12+i]. */
    if (v[3] != 0 || v[7] != 0 || v[11] != 0 || v[15] != 1)
        return fail_at(p, d, BRT_EPARSE, "only affine matrices are read (numbers 4, 8, 12, 16 must be 0 0 0 1)");
    for (i = 0; i < 3; i++) {
        m[4 * i] = v[i]; m[4 * i + 1] = v[4 + i]; m[4 * i + 2] = v[8 + i]; m[4 * i + 3] = v[12 + i];
    }
    if (concat) apply(p, m);
    else if (p->g.start_active) memcpy(p->g.ctm, m, sizeof m);
    return BRT_OK;
}

static brt_result do_simple_transform(parser *p, const token *d)
{
    double v[9], m[12];
    brt_result r;
    xf_identity(m);
    if (token_is(d, "Translate")) {
        if ((r = expect_numbers(p, v, 3)) != BRT_OK) return r;
        m[3] = v[0]; m[7] = v[1]; m[11] = v[2];
    } else if (token_is(d, "Scale")) {
        if ((r = expect_numbers(p, v, 3)) != BRT_OK) return r;
        m[0] = v[0]; m[5] = v[1]; m[10] = v[2];
    } else if (token_is(d, "Rotate")) {
        if ((r = expect_numbers(p, v, 4)) != BRT_OK) return r;
        if (!xf_rotate(v[0], v[1], v[2], v[3], m)) return fail_at(p, d, BRT_EPARSE, "Rotate about a zero axis");
    } else {   /* LookAt */
        if ((r = expect_numbers(p, v, 9)) != BRT_OK) return r;
        if (!xf_look_at(v, m))
            return fail_at(p, d, BRT_EPARSE, "LookAt: the up vector is zero or parallel to the view direction");
    }
    apply(p, m);
    return BRT_OK;
}

static named_xf *find_named(parser *p, const char *name)
{
    size_t i;
    for (i = 0; i < p->named_count; i++)
        if (strcmp(p->named[i].name, name) == 0) return &p->named[i];
    return NULL;
}

/* CoordinateSystem "name" records the CTM (a new one replaces the old). */
static brt_result set_named(parser *p, const char *name, const double m[12])
{
    named_xf *n = find_named(p, name);
    if (!n) {
        if (GROW(p, p->named, p->named_count, p->named_cap)) return BRT_ENOMEM;
        n = &p->named[p->named_count];
        if (!(n->name = malloc(strlen(name) + 1))) return brt_fail(p->err, BRT_ENOMEM, "out of memory");
        strcpy(n->name, name);
        p->named_count++;
    }
    memcpy(n->m, m, sizeof n->m);
    return BRT_OK;
}

static brt_result do_coordinates(parser *p, const token *d)
{
    char name[256];
    token t;
    int define = token_is(d, "CoordinateSystem");
    brt_result r = expect_string(p, define ? "CoordinateSystem" : "CoordSysTransform", name, sizeof name, &t);
    named_xf *n;
    if (r != BRT_OK) return r;
    if (define) return set_named(p, name, p->g.ctm);
    n = find_named(p, name);
    if (n) { memcpy(p->g.ctm, n->m, sizeof n->m); return BRT_OK; }
    /* pbrt warns and goes on; so do we, and the summary says so. */
    {
        char key[96];
        snprintf(key, sizeof key, "CoordSysTransform \"%.40s\" (unknown)", name);
        return count_skipped(p, key);
    }
}

static brt_result push_state(parser *p, char kind, const token *d)
{
    if (GROW(p, p->stack, p->stack_count, p->stack_cap)) return BRT_ENOMEM;
    p->g.kind = kind;
    p->g.file = d->file;
    p->g.line = (uint32_t)d->line;
    p->stack[p->stack_count++] = p->g;
    return BRT_OK;
}

/* Blocks close in the order they opened, each with its own End: pbrt-v4
** reads TransformBegin/End as AttributeBegin/End, but a file that closes
** one with the other's End is a mistake, refused here. */
static brt_result pop_state(parser *p, char kind, const token *d)
{
    const char *what = kind == 'a' ? "AttributeEnd" : kind == 't' ? "TransformEnd" : "ObjectEnd";
    gstate *top;
    if (p->stack_count == p->frames[p->depth - 1].base)   /* an Import's blocks are its own */
        return fail_at(p, d, BRT_EPARSE, "%s without %s", what, block_begin(kind));
    top = &p->stack[p->stack_count - 1];
    if (top->kind != kind)
        return fail_at(p, d, BRT_EPARSE, "%s while the %s at %s:%lu is open", what, block_begin(top->kind),
                       p->scene->files[top->file], (unsigned long)top->line);
    p->g = *top;
    p->stack_count--;
    return BRT_OK;
}

/* FNV-1a of a name, for the object table. */
static uint64_t name_hash(const char *s)
{
    uint64_t h = 14695981039346656037ull;
    for (; *s; s++) h = (h ^ (unsigned char)*s) * 1099511628211ull;
    return h;
}

/* The slot of an object name, created on first mention. */
static brt_result object_slot(parser *p, const char *name, uint32_t *slot)
{
    ex_pbrt *s = p->scene;
    size_t mask, i;
    if (2 * ((size_t)s->object_count + 1) > s->hash_cap) {   /* rehash at half full */
        size_t cap = s->hash_cap ? 2 * s->hash_cap : 64, k;
        uint32_t *table = calloc(cap, sizeof *table);
        if (!table) return brt_fail(p->err, BRT_ENOMEM, "out of memory");
        for (k = 0; k < s->object_count; k++) {
            for (i = name_hash(s->objects[k].name) & (cap - 1); table[i]; i = (i + 1) & (cap - 1)) {}
            table[i] = (uint32_t)k + 1;
        }
        free(s->slot_of);
        s->slot_of = table;
        s->hash_cap = cap;
    }
    mask = s->hash_cap - 1;
    for (i = name_hash(name) & mask; s->slot_of[i]; i = (i + 1) & mask)
        if (strcmp(s->objects[s->slot_of[i] - 1].name, name) == 0) { *slot = s->slot_of[i] - 1; return BRT_OK; }
    if (GROW(p, s->objects, s->object_count, s->object_cap)) return BRT_ENOMEM;
    memset(&s->objects[s->object_count], 0, sizeof *s->objects);
    if (!(s->objects[s->object_count].name = malloc(strlen(name) + 1)))
        return brt_fail(p->err, BRT_ENOMEM, "out of memory");
    strcpy(s->objects[s->object_count].name, name);
    s->slot_of[i] = s->object_count + 1;
    *slot = s->object_count++;
    return BRT_OK;
}

static brt_result do_object_begin(parser *p, const token *d)
{
    ex_pbrt *s = p->scene;
    char name[1024];
    token t;
    uint32_t slot;
    brt_result r = expect_string(p, "ObjectBegin", name, sizeof name, &t);
    if (r != BRT_OK) return r;
    if (p->object != NO_OBJECT)
        return fail_at(p, d, BRT_EPARSE, "ObjectBegin \"%s\" inside ObjectBegin \"%s\"", name, s->objects[p->object].name);
    if ((r = object_slot(p, name, &slot)) != BRT_OK) return r;
    if (s->objects[slot].defined) return fail_at(p, d, BRT_EPARSE, "object \"%s\" defined twice", name);
    if (s->prototype_count == 0xFFFFFFFFu) return fail_at(p, d, BRT_EPARSE, "too many objects");
    if (GROW(p, s->prototypes, s->prototype_count, s->prototype_cap)) return BRT_ENOMEM;
    s->objects[slot].defined = 1;
    s->objects[slot].prototype = s->prototype_count;
    s->objects[slot].first_shape = (uint32_t)s->shape_count;
    s->prototypes[s->prototype_count++] = slot;
    p->object = slot;
    return push_state(p, 'o', d);
}

static brt_result do_object_end(parser *p, const token *d)
{
    ex_pbrt *s = p->scene;
    brt_result r = pop_state(p, 'o', d);
    if (r != BRT_OK) return r;
    s->objects[p->object].shape_count = (uint32_t)(s->shape_count - s->objects[p->object].first_shape);
    p->object = NO_OBJECT;
    return BRT_OK;
}

static brt_result do_object_instance(parser *p, const token *d)
{
    ex_pbrt *s = p->scene;
    char name[1024];
    token t;
    uint32_t slot;
    brt_instance *inst;
    int k;
    brt_result r = expect_string(p, "ObjectInstance", name, sizeof name, &t);
    if (r != BRT_OK) return r;
    if (p->object != NO_OBJECT)
        return fail_at(p, d, BRT_EPARSE, "ObjectInstance \"%s\" inside ObjectBegin \"%s\" (one level of instancing only)",
                       name, s->objects[p->object].name);
    if ((r = check_ctm(p, d, "ObjectInstance")) != BRT_OK) return r;
    if ((r = object_slot(p, name, &slot)) != BRT_OK) return r;
    if (s->instance_count == 0xFFFFFFFFu) return fail_at(p, d, BRT_EPARSE, "more than 2^32-1 instances");
    if (GROW(p, s->instances, s->instance_count, s->instance_cap)) return BRT_ENOMEM;
    if (!s->objects[slot].defined && s->objects[slot].use_line == 0) {
        s->objects[slot].use_file = d->file;
        s->objects[slot].use_line = (uint32_t)d->line;
    }
    inst = &s->instances[s->instance_count];
    inst->prototype = slot;   /* a slot until the end of pass 1 (finish) */
    for (k = 0; k < 12; k++)
        if (!isfinite(inst->xform[k] = (float)p->g.ctm[k]))
            return fail_at(p, d, BRT_EPARSE, "ObjectInstance: the transform is not finite in float");
    s->instance_count++;
    return BRT_OK;
}

/* Checks a triangle shape's parameters once read (see the header). */
static brt_result check_mesh(parser *p, const token *d, wanted *w, const char *name)
{
    int bilinear = w->shape_kind == SHAPE_BILINEAR;
    uint64_t per = bilinear ? 4 : 3, verts = w->p_count / 3;
    if (!w->has_p) return fail_at(p, d, BRT_EPARSE, "Shape \"%s\" without \"point3 P\"", name);
    if (w->p_count % 3 != 0)
        return fail_at(p, d, BRT_EPARSE, "Shape \"%s\": \"P\" has %llu numbers, not a multiple of 3", name,
                       (unsigned long long)w->p_count);
    if (!w->has_i) {
        if (verts != per)
            return fail_at(p, d, BRT_EPARSE, "Shape \"%s\": \"indices\" missing (only %d points may go without)",
                           name, (int)per);
        return BRT_OK;
    }
    if (w->i_count % per != 0)
        return fail_at(p, d, BRT_EPARSE, "Shape \"%s\": \"indices\" has %llu numbers, not a multiple of %d", name,
                       (unsigned long long)w->i_count, (int)per);
    if (w->i_count > 0 && w->i_max >= verts)
        return fail_at(p, &w->i_token, BRT_EPARSE, "Shape \"%s\": index %lu out of range (%llu vertices)", name,
                       (unsigned long)w->i_max, (unsigned long long)verts);
    return BRT_OK;
}

static brt_result add_shape(parser *p, const token *d, const wanted *w)
{
    ex_pbrt *s = p->scene;
    double identity[12];
    shape *sh;
    if (GROW(p, s->shapes, s->shape_count, s->shape_cap)) return BRT_ENOMEM;
    sh = &s->shapes[s->shape_count++];
    memset(sh, 0, sizeof *sh);
    memcpy(sh->xform, p->g.ctm, sizeof sh->xform);
    xf_identity(identity);
    sh->identity = memcmp(identity, sh->xform, sizeof identity) == 0;
    sh->kind = w->shape_kind;
    sh->levels = w->levels;
    sh->p_offset = w->p_offset; sh->p_line = w->p_line; sh->p_count = w->p_count; sh->p_file = w->p_file;
    sh->i_offset = w->i_offset; sh->i_line = w->i_line; sh->i_count = w->i_count;
    sh->has_indices = w->has_i;
    sh->i_file = w->i_file;
    sh->object = p->object;
    sh->line = (uint32_t)d->line;
    sh->file = d->file;
    if (p->object == NO_OBJECT) s->world_shapes++;
    return BRT_OK;
}

static brt_result do_shape(parser *p, const token *d)
{
    char name[128], key[160], path[4096];
    token t;
    wanted w;
    brt_result r = expect_string(p, "Shape", name, sizeof name, &t);
    if (r != BRT_OK) return r;
    memset(&w, 0, sizeof w);
    w.shape_kind = strcmp(name, "trianglemesh") == 0 ? SHAPE_TRIANGLES
                 : strcmp(name, "bilinearmesh") == 0 ? SHAPE_BILINEAR
                 : strcmp(name, "plymesh") == 0 ? SHAPE_PLY
                 : strcmp(name, "loopsubdiv") == 0 ? SHAPE_LOOP : -1;
    w.report = w.shape_kind >= 0 ? "Shape" : NULL;
    w.levels = 3;           /* pbrt-v4's default */
    if ((r = read_params(p, &w)) != BRT_OK) return r;
    if (w.shape_kind < 0) {
        snprintf(key, sizeof key, "Shape \"%.80s\"", name);
        return count_skipped(p, key);
    }
    if ((r = check_ctm(p, d, "Shape")) != BRT_OK) return r;
    if (w.shape_kind == SHAPE_PLY) {
        long file;
        if (!w.has_filename) return fail_at(p, d, BRT_EPARSE, "Shape \"plymesh\" without \"string filename\"");
        if (!resolve(p, w.filename, path, sizeof path)) return fail_at(p, d, BRT_EPARSE, "file name too long");
        if (access(path, R_OK) != 0)
            return fail_at(p, d, BRT_EIO, "plymesh \"%s\": cannot read %s: %s", w.filename, path, strerror(errno));
        if ((file = add_file(p, path)) < 0) return BRT_ENOMEM;
        w.p_file = (uint32_t)file;
    } else if (w.shape_kind == SHAPE_LOOP && (!w.has_i || w.i_count == 0)) {
        /* pbrt-v4 stops here too: a loopsubdiv's indices are never implied */
        return fail_at(p, d, BRT_EPARSE, "Shape \"loopsubdiv\" without \"integer indices\"");
    } else if ((r = check_mesh(p, d, &w, name)) != BRT_OK) return r;
    /* Its vertices and triangles are numbered in 32 bits while refined. */
    if (w.shape_kind == SHAPE_LOOP && (ex_loop_triangle_count(w.i_count / 3, w.levels) > EX_LOOP_MAX_TRIANGLES
                                       || w.p_count / 3 > EX_LOOP_MAX_TRIANGLES))
        return fail_at(p, d, BRT_EPARSE, "Shape \"loopsubdiv\": %llu faces at levels %d make more than %lu triangles",
                       (unsigned long long)(w.i_count / 3), w.levels, (unsigned long)EX_LOOP_MAX_TRIANGLES);
    /* Checked as any shape is, then dropped: pbrt-v4 never hits it. */
    if (w.alpha == ALPHA_ZERO) return count_skipped(p, "Shape removed by \"alpha\" 0");
    if (w.alpha == ALPHA_PARTIAL) r = count_skipped(p, "Shape parameter \"alpha\" (kept opaque)");
    if (w.alpha == ALPHA_TEXTURE) r = count_skipped(p, "Shape parameter \"texture alpha\" (kept opaque)");
    return r != BRT_OK ? r : add_shape(p, d, &w);
}

static brt_result do_camera(parser *p, const token *d)
{
    ex_pbrt *s = p->scene;
    char name[128], key[160];
    double w2c[12], dir[3], up[3], right[3];
    token t;
    wanted w;
    int k;
    brt_result r = expect_string(p, "Camera", name, sizeof name, &t);
    if (r != BRT_OK) return r;
    memset(&w, 0, sizeof w);
    w.shape_kind = -1;
    w.camera = strcmp(name, "perspective") == 0;
    w.report = w.camera ? "Camera" : NULL;
    w.fov = 90;   /* pbrt's default */
    if ((r = read_params(p, &w)) != BRT_OK) return r;
    if (w.screen_n != 0 && w.screen_n != 4)
        return fail_at(p, &w.screen_at, BRT_EPARSE, "\"screenwindow\": %d numbers, expected 4 (x0 x1 y0 y1)",
                       w.screen_n);
    if (w.screen_n == 4 && !(w.screen[0] != w.screen[1] && w.screen[2] != w.screen[3]))
        return fail_at(p, &w.screen_at, BRT_EPARSE, "\"screenwindow\": an empty window");
    if (!xf_invert(p->g.ctm, w2c)) return fail_at(p, d, BRT_EPARSE, "Camera: singular transform (determinant 0)");
    if ((r = set_named(p, "camera", w2c)) != BRT_OK) return r;
    if (!w.camera) {
        snprintf(key, sizeof key, "Camera \"%.80s\"", name);
        return count_skipped(p, key);
    }
    /* Camera axes in world space: the columns of world-from-camera. */
    for (k = 0; k < 3; k++) {
        right[k] = w2c[4 * k];
        up[k] = w2c[4 * k + 1];
        dir[k] = w2c[4 * k + 2];
    }
    normalize(dir);
    normalize(up);
    s->has_camera = 1;
    s->fov = (float)w.fov;
    memcpy(s->world_from_camera, w2c, sizeof w2c);
    s->has_screen = w.screen_n == 4;
    memcpy(s->screen, w.screen, sizeof s->screen);
    s->frame = w.has_frame ? w.frame : 0;
    for (k = 0; k < 3; k++) {
        s->eye[k] = (float)w2c[4 * k + 3];
        s->target[k] = (float)(w2c[4 * k + 3] + dir[k]);
        s->up[k] = (float)up[k];
        if (!isfinite(s->eye[k]) || !isfinite(s->target[k]))
            return fail_at(p, d, BRT_EPARSE, "Camera: the camera position is not finite in float");
    }
    /* Mirrored when camera +x (pbrt's image right) opposes forward x up. */
    s->mirrored = right[0] * (dir[1] * up[2] - dir[2] * up[1]) + right[1] * (dir[2] * up[0] - dir[0] * up[2])
                + right[2] * (dir[0] * up[1] - dir[1] * up[0]) < 0;
    return BRT_OK;
}

/* Film: only its resolution is read (pbrt-v4's film.cpp defaults). */
static brt_result do_film(parser *p, const token *d)
{
    char name[128];
    token t;
    wanted w;
    brt_result r = expect_string(p, "Film", name, sizeof name, &t);
    if (r != BRT_OK) return r;
    memset(&w, 0, sizeof w);
    w.shape_kind = -1;
    w.film = 1;
    w.report = "Film";
    w.xres = 1280;
    w.yres = 720;
    if ((r = read_params(p, &w)) != BRT_OK) return r;
    (void)d;
    p->scene->has_film = 1;
    p->scene->film_width = w.xres;
    p->scene->film_height = w.yres;
    return BRT_OK;
}

static brt_result do_include(parser *p, const token *d)
{
    char name[4096], path[4096];
    token t;
    brt_result r = expect_string(p, token_is(d, "Include") ? "Include" : "Import", name, sizeof name, &t);
    if (r != BRT_OK) return r;
    if (!resolve(p, name, path, sizeof path)) return fail_at(p, &t, BRT_EPARSE, "file name too long");
    return push_file(p, path, d, token_is(d, "Import"));
}

/* Directives whose arguments are a type name and a parameter list, all
** skipped (and counted). */
static brt_result skip_named_params(parser *p, const token *d, const char *key, int strings)
{
    char b[1024];
    token t;
    wanted w;
    int i;
    brt_result r;
    for (i = 0; i < strings; i++)
        if ((r = expect_string(p, key, b, sizeof b, &t)) != BRT_OK) return r;
    memset(&w, 0, sizeof w);
    w.shape_kind = -1;
    if ((r = read_params(p, &w)) != BRT_OK) return r;
    (void)d;
    return count_skipped(p, key);
}

/* The directives with fixed arguments that are skipped: MediumInterface
** (one or two strings), Option (a declaration and one value), ActiveTransform,
** TransformTimes, NamedMaterial, ColorSpace, ReverseOrientation. */
static brt_result skip_other(parser *p, const token *d, const char *key)
{
    char b[1024], shown_buf[40];
    double v[2];
    token t;
    brt_result r = BRT_OK;
    if (strcmp(key, "MediumInterface") == 0) {
        if ((r = expect_string(p, key, b, sizeof b, &t)) != BRT_OK) return r;
        if ((r = next(p, &t)) != BRT_OK) return r;
        if (t.kind != TOK_STRING) unget(p, &t);
    } else if (strcmp(key, "Option") == 0) {
        if ((r = expect_string(p, key, b, sizeof b, &t)) != BRT_OK) return r;
        if ((r = next(p, &t)) != BRT_OK) return r;
        if (t.kind != TOK_WORD && t.kind != TOK_STRING)
            return fail_at(p, &t, BRT_EPARSE, "Option: expected a value, got '%s'", shown(&t, shown_buf, sizeof shown_buf));
    } else if (strcmp(key, "ActiveTransform") == 0) {
        if ((r = next(p, &t)) != BRT_OK) return r;
        if (token_is(&t, "All") || token_is(&t, "StartTime")) p->g.start_active = 1;
        else if (token_is(&t, "EndTime")) p->g.start_active = 0;
        else return fail_at(p, &t, BRT_EPARSE, "ActiveTransform: expected All, StartTime or EndTime");
    } else if (strcmp(key, "TransformTimes") == 0) {
        r = expect_numbers(p, v, 2);
    } else if (strcmp(key, "NamedMaterial") == 0 || strcmp(key, "ColorSpace") == 0) {
        r = expect_string(p, key, b, sizeof b, &t);
    }
    (void)d;
    return r != BRT_OK ? r : count_skipped(p, key);
}

/* One directive at token d. */
static brt_result directive(parser *p, const token *d)
{
    static const char *const with_params[] = {
        "Sampler", "Integrator", "Accelerator", "PixelFilter", "LightSource",
        "AreaLightSource", "Material", "MakeNamedMaterial", "MakeNamedMedium", "Attribute"};
    static const char *const others[] = {"MediumInterface", "Option", "ActiveTransform", "TransformTimes",
                                         "NamedMaterial", "ColorSpace", "ReverseOrientation"};
    char b[40];
    size_t i;
    if (token_is(d, "Shape")) return do_shape(p, d);
    if (token_is(d, "AttributeBegin")) return push_state(p, 'a', d);
    if (token_is(d, "TransformBegin")) return push_state(p, 't', d);
    if (token_is(d, "AttributeEnd")) return pop_state(p, 'a', d);
    if (token_is(d, "TransformEnd")) return pop_state(p, 't', d);
    if (token_is(d, "Film")) return do_film(p, d);
    if (token_is(d, "ObjectInstance")) return do_object_instance(p, d);
    if (token_is(d, "Translate") || token_is(d, "Scale") || token_is(d, "Rotate") || token_is(d, "LookAt"))
        return do_simple_transform(p, d);
    if (token_is(d, "Transform")) return do_transform(p, d, 0);
    if (token_is(d, "ConcatTransform")) return do_transform(p, d, 1);
    if (token_is(d, "Identity")) { if (p->g.start_active) xf_identity(p->g.ctm); return BRT_OK; }
    if (token_is(d, "ObjectBegin")) return do_object_begin(p, d);
    if (token_is(d, "ObjectEnd")) return do_object_end(p, d);
    if (token_is(d, "CoordinateSystem") || token_is(d, "CoordSysTransform")) return do_coordinates(p, d);
    if (token_is(d, "Include") || token_is(d, "Import")) return do_include(p, d);
    if (token_is(d, "Camera")) return do_camera(p, d);
    if (token_is(d, "WorldBegin")) {
        xf_identity(p->g.ctm);
        p->g.start_active = 1;
        return set_named(p, "world", p->g.ctm);
    }
    if (token_is(d, "WorldEnd")) return count_skipped(p, "WorldEnd");   /* pbrt-v3's */
    if (token_is(d, "Texture")) return skip_named_params(p, d, "Texture", 3);
    for (i = 0; i < sizeof with_params / sizeof *with_params; i++)
        if (token_is(d, with_params[i])) return skip_named_params(p, d, with_params[i], 1);
    for (i = 0; i < sizeof others / sizeof *others; i++)
        if (token_is(d, others[i])) return skip_other(p, d, others[i]);
    if (d->kind == TOK_WORD) return fail_at(p, d, BRT_EPARSE, "unknown directive '%s'", shown(d, b, sizeof b));
    return fail_at(p, d, BRT_EPARSE, "expected a directive, got '%s'", shown(d, b, sizeof b));
}

/* After the last token: every open block closed, every instanced object
** defined; instances' slots become prototype numbers; the summary. */
static brt_result finish(parser *p)
{
    ex_pbrt *s = p->scene;
    size_t i, len = 0;
    if (p->stack_count > 0) return never_closed(p, &p->stack[p->stack_count - 1]);
    for (i = 0; i < s->object_count; i++)
        if (!s->objects[i].defined)
            return brt_fail(p->err, BRT_EPARSE, "%s:%lu: ObjectInstance of unknown object \"%s\"",
                            s->files[s->objects[i].use_file], (unsigned long)s->objects[i].use_line,
                            s->objects[i].name);
    for (i = 0; i < s->instance_count; i++)
        s->instances[i].prototype = s->objects[s->instances[i].prototype].prototype;
    for (i = 0; i < s->skip_count; i++) len += strlen(s->skipped[i].key) + 40;
    if (!(s->summary = malloc(len + 16))) return brt_fail(p->err, BRT_ENOMEM, "out of memory");
    s->summary[0] = 0;
    for (i = 0, len = 0; i < s->skip_count; i++)
        len += (size_t)sprintf(s->summary + len, "%s%llu %s", i ? ", " : "skipped: ",
                               (unsigned long long)s->skipped[i].count, s->skipped[i].key);
    return BRT_OK;
}

/* The folder part of path ("" for a bare name). */
static char *folder_of(const char *path)
{
    const char *slash = strrchr(path, '/');
    size_t n = slash ? (size_t)(slash - path) : 0;
    char *f = malloc(n + 2);
    if (!f) return NULL;
    if (slash && n == 0) n = 1;   /* "/scene.pbrt": the root */
    memcpy(f, path, n);
    f[n] = 0;
    return f;
}

static brt_result parse(parser *p, const char *path)
{
    token t;
    brt_result r;
    if (!(p->scene->folder = folder_of(path))) return brt_fail(p->err, BRT_ENOMEM, "out of memory");
    if (add_file(p, path) < 0) return BRT_ENOMEM;
    if ((r = reader_open(&p->files[0], p->scene->files[0], 0, PASS1_WINDOW, p->err)) != BRT_OK) return r;
    p->depth = 1;
    for (;;) {
        if ((r = next(p, &t)) != BRT_OK) return r;
        if (t.kind == TOK_EOF && p->depth == 1) return finish(p);
        if (t.kind == TOK_EOF) {
            if ((r = end_import(p)) != BRT_OK) return r;
            continue;
        }
        if ((r = directive(p, &t)) != BRT_OK) return r;
    }
}

/* ===================================================================== */
/* Part V: pass 2, the streams                                           */
/* ===================================================================== */

/* Triangles on their way to the consumer, in chunks of CHUNK_TRIS. */
typedef struct sink {
    float *corners;
    uint32_t count;
    uint64_t first;         /* number of the chunk's first triangle */
    brt_triangle_fn emit;
    void *user;
    brt_error *err;
} sink;

static brt_result sink_flush(sink *k)
{
    brt_result r;
    if (k->count == 0) return BRT_OK;
    if (k->first + k->count > 0xFFFFFFFFu)
        return brt_fail(k->err, BRT_EPARSE, "more than 2^32-1 triangles (the miss record's number)");
    r = k->emit(k->user, k->corners, k->count, (uint32_t)k->first, k->err);
    k->first += k->count;
    k->count = 0;
    return r;
}

static brt_result sink_add(sink *k, const float *a, const float *b, const float *c)
{
    float *o = k->corners + 9 * (size_t)k->count;
    memcpy(o, a, 3 * sizeof *a);
    memcpy(o + 3, b, 3 * sizeof *b);
    memcpy(o + 6, c, 3 * sizeof *c);
    return ++k->count == CHUNK_TRIS ? sink_flush(k) : BRT_OK;
}

/* What one run of a stream holds: the sink, a reader over the current
** file, and one shape's vertex positions. */
typedef struct run {
    const ex_pbrt *scene;
    sink out;
    reader in;
    float *positions;
    size_t position_cap;
    uint32_t face[4];       /* the patch being read */
    int corners;            /* of it read so far */
    uint32_t *indices;      /* a loopsubdiv's, held whole while refined */
    size_t index_cap;
} run;

static brt_result run_changed(run *u, const shape *sh)
{
    return brt_fail(u->out.err, BRT_EIO, "%s:%lu: the file changed since it was opened (Shape's numbers differ)",
                    u->scene->files[sh->file], (unsigned long)sh->line);
}

/* Positions the run's reader at offset of file, opening it if needed. */
static brt_result run_seek(run *u, uint32_t file, uint64_t offset, uint64_t line)
{
    brt_result r;
    if (u->in.buf == NULL || u->in.file != file) {
        if (u->in.buf) reader_close(&u->in);
        r = reader_open(&u->in, u->scene->files[file], file, PASS2_WINDOW, u->out.err);
        if (r != BRT_OK) return r;
    }
    if (reader_seek(&u->in, offset, line) != 0)
        return brt_fail(u->out.err, BRT_EIO, "%s: %s", u->scene->files[file], strerror(errno));
    return BRT_OK;
}

/* Reads count numbers of a value recorded in pass 1 ('[' n... ']' or one
** number) and hands each to fn: its text (s, n) and its scan d. */
typedef brt_result (*number_fn)(run *u, const char *s, size_t n, const decimal *d, uint64_t i,
                                const shape *sh);

/* A number through next_token (the slow path); 0 when not one. */
static int token_number(const token *t, decimal *d)
{
    const char *c = t->s;
    return t->kind == TOK_WORD && scan_decimal(&c, d, 1) == DEC_OK && c == t->s + t->n;
}

/* Inlined at its two calls, so that fn is known there and its call is
** direct (make bench-pbrt). */
#if defined(__GNUC__)
static inline brt_result run_numbers(run *u, const shape *sh, uint32_t file, uint64_t offset, uint64_t line,
                                     uint64_t count, number_fn fn) __attribute__((always_inline));
#endif
static inline brt_result run_numbers(run *u, const shape *sh, uint32_t file, uint64_t offset, uint64_t line,
                                     uint64_t count, number_fn fn)
{
    token t;
    decimal d;
    uint64_t i;
    int bracket;
    brt_result r = run_seek(u, file, offset, line);
    if (r != BRT_OK || (r = next_token(&u->in, &t, u->out.err)) != BRT_OK) return r;
    bracket = t.kind == TOK_OPEN;
    if (!bracket && count != 1) return run_changed(u, sh);
    for (i = 0; i < count; i++) {
        size_t n = 0;
        if (bracket) {
            const char *c = u->in.buf + u->in.pos;
            n = number_at(&c, u->in.buf + u->in.end, &u->in.line, &d, 1);
            u->in.pos = (size_t)(c - u->in.buf) + n;
            t.s = c;
            t.n = n;
        }
        if (n == 0) {
            if (bracket && (r = next_token(&u->in, &t, u->out.err)) != BRT_OK) return r;
            if (!token_number(&t, &d)) return run_changed(u, sh);
        }
        if ((r = fn(u, t.s, t.n, &d, i, sh)) != BRT_OK) return r;
    }
    if (bracket && ((r = next_token(&u->in, &t, u->out.err)) != BRT_OK || t.kind != TOK_CLOSE))
        return r != BRT_OK ? r : run_changed(u, sh);
    return BRT_OK;
}

/* A point through a shape's transform may overflow the float range,
** which pass 1 (numbers only) cannot see: the shape is refused then. */
static brt_result transform_point(brt_error *err, const ex_pbrt *scene, const shape *sh, const float p[3],
                                  float out[3])
{
    xf_point(sh->xform, p, out);
    if (isfinite(out[0]) && isfinite(out[1]) && isfinite(out[2])) return BRT_OK;
    return brt_fail(err, BRT_EPARSE, "%s:%lu: Shape: a point is not finite in float after the transform in force",
                    scene->files[sh->file], (unsigned long)sh->line);
}

static brt_result number_position(run *u, const char *s, size_t n, const decimal *d, uint64_t i,
                                  const shape *sh)
{
    float f;
    if (decimal_float(d, s, n, &f) != NUM_OK) return run_changed(u, sh);
    u->positions[i] = f;
    /* xf_point gives an identity's points back bit for bit: skipped.  A
    ** loopsubdiv is refined in object space and its limit points
    ** transformed after, as pbrt-v4's TriangleMesh does. */
    if (i % 3 != 2 || sh->identity || sh->kind == SHAPE_LOOP) return BRT_OK;
    return transform_point(u->out.err, u->scene, sh, &u->positions[i - 2], &u->positions[i - 2]);
}

/* Indices are handed on a patch at a time: 3 (a triangle) or 4 (a
** bilinear patch: (a,b,d) and (a,d,c), see the header). */
static brt_result emit_face(run *u, const uint32_t *v, int bilinear)
{
    const float *p = u->positions;
    brt_result r = sink_add(&u->out, p + 3 * (size_t)v[0], p + 3 * (size_t)v[1], p + 3 * (size_t)v[bilinear ? 3 : 2]);
    if (r != BRT_OK || !bilinear) return r;
    return sink_add(&u->out, p + 3 * (size_t)v[0], p + 3 * (size_t)v[3], p + 3 * (size_t)v[2]);
}

static brt_result number_index(run *u, const char *s, size_t n, const decimal *d, uint64_t i,
                               const shape *sh)
{
    int bilinear = sh->kind == SHAPE_BILINEAR;
    uint32_t *v = &u->face[u->corners];
    (void)s;
    (void)i;
    if (!decimal_index(d, n, v) || *v >= sh->p_count / 3) return run_changed(u, sh);
    if (++u->corners < 3 + bilinear) return BRT_OK;
    u->corners = 0;
    return emit_face(u, u->face, bilinear);
}

/* A shape's positions into the run's buffer (grown to hold them). */
static brt_result run_positions(run *u, const shape *sh)
{
    size_t need = (size_t)sh->p_count;
    if (need > u->position_cap || !u->positions) {
        float *bigger = realloc(u->positions, (need ? need : 1) * sizeof *bigger);
        if (!bigger) return brt_fail(u->out.err, BRT_ENOMEM, "out of memory for %llu vertices",
                                     (unsigned long long)(sh->p_count / 3));
        u->positions = bigger;
        u->position_cap = need;
    }
    return run_numbers(u, sh, sh->p_file, sh->p_offset, sh->p_line, sh->p_count, number_position);
}

/* A trianglemesh or bilinearmesh: positions first (they may come after
** the indices in the file), then the indices, streamed. */
static brt_result run_mesh(run *u, const shape *sh)
{
    static const uint32_t implicit[4] = {0, 1, 2, 3};
    brt_result r;
    r = run_positions(u, sh);
    if (r != BRT_OK) return r;
    if (!sh->has_indices) return emit_face(u, implicit, sh->kind == SHAPE_BILINEAR);
    u->corners = 0;
    return run_numbers(u, sh, sh->i_file, sh->i_offset, sh->i_line, sh->i_count, number_index);
}

/* A loopsubdiv's index, kept (range checked again: the file may change). */
static brt_result number_loop_index(run *u, const char *s, size_t n, const decimal *d, uint64_t i,
                                    const shape *sh)
{
    (void)s;
    if (!decimal_index(d, n, &u->indices[i]) || u->indices[i] >= sh->p_count / 3) return run_changed(u, sh);
    return BRT_OK;
}

/* A loopsubdiv's indices, whole, into u->indices. */
static brt_result run_loop_indices(run *u, const shape *sh)
{
    if (sh->i_count > u->index_cap) {
        uint32_t *bigger = realloc(u->indices, (size_t)sh->i_count * sizeof *bigger);
        if (!bigger) return brt_fail(u->out.err, BRT_ENOMEM, "out of memory for %llu indices",
                                     (unsigned long long)sh->i_count);
        u->indices = bigger;
        u->index_cap = (size_t)sh->i_count;
    }
    return run_numbers(u, sh, sh->i_file, sh->i_offset, sh->i_line, sh->i_count, number_loop_index);
}

/* A message of examples/lib/loopsubdiv.c, at the shape's file and line. */
static brt_result loop_failed(const ex_pbrt *scene, const shape *sh, brt_result r, brt_error *err)
{
    brt_error inner;
    if (!err) return r;
    inner = *err;
    return brt_fail(err, r, "%s:%lu: Shape \"loopsubdiv\": %s", scene->files[sh->file], (unsigned long)sh->line,
                    inner.message);
}

/* A loopsubdiv: the control mesh read whole (object space), refined as
** pbrt-v4 refines it (examples/lib/loopsubdiv.h), its limit points put
** through the shape's transform, its triangles emitted in pbrt's order. */
static brt_result run_loop(run *u, const shape *sh)
{
    ex_loop_mesh m;
    uint32_t i;
    brt_result r;
    r = run_positions(u, sh);
    if (r != BRT_OK || (r = run_loop_indices(u, sh)) != BRT_OK) return r;
    r = ex_loop_subdivide(u->positions, (uint32_t)(sh->p_count / 3), u->indices, (uint32_t)(sh->i_count / 3),
                          sh->levels, &m, u->out.err);
    if (r != BRT_OK) return loop_failed(u->scene, sh, r, u->out.err);
    for (i = 0; i < m.vertex_count && r == BRT_OK && !sh->identity; i++)
        r = transform_point(u->out.err, u->scene, sh, m.p + 3 * (size_t)i, m.p + 3 * (size_t)i);
    for (i = 0; i < m.triangle_count && r == BRT_OK; i++) {
        const uint32_t *t = m.indices + 3 * (size_t)i;
        r = sink_add(&u->out, m.p + 3 * (size_t)t[0], m.p + 3 * (size_t)t[1], m.p + 3 * (size_t)t[2]);
    }
    ex_loop_free(&m);
    return r;
}

/* A PLY mesh's chunks, transformed, into the run's sink. */
typedef struct ply_pass { run *u; const shape *sh; } ply_pass;

static brt_result ply_chunk(void *user, const float *corners, uint32_t count, uint32_t first, brt_error *err)
{
    ply_pass *pp = user;
    uint32_t i;
    (void)first;
    (void)err;
    for (i = 0; i < count; i++) {
        float c[9];
        brt_result r = BRT_OK;
        int k;
        for (k = 0; k < 3 && r == BRT_OK; k++)
            r = transform_point(pp->u->out.err, pp->u->scene, pp->sh, corners + 9 * (size_t)i + 3 * k, c + 3 * k);
        if (r != BRT_OK || (r = sink_add(&pp->u->out, c, c + 3, c + 6)) != BRT_OK) return r;
    }
    return BRT_OK;
}

/* "gzip -dc path" into a new temporary file under $TMPDIR, named in tmp. */
static brt_result gunzip(const char *path, char *tmp, size_t size, brt_error *err)
{
    const char *dir = getenv("TMPDIR");
    int fd, status;
    pid_t pid;
    snprintf(tmp, size, "%s/batchrt-ply-XXXXXX", dir && *dir ? dir : "/tmp");
    if ((fd = mkstemp(tmp)) < 0) {
        brt_result r = brt_fail(err, BRT_EIO, "%s: cannot make a temporary file %s: %s", path, tmp, strerror(errno));
        tmp[0] = 0;
        return r;
    }
    pid = fork();
    if (pid == 0) {
        int null = open("/dev/null", O_WRONLY);   /* our message says what failed */
        if (dup2(fd, 1) < 0 || (null >= 0 && dup2(null, 2) < 0)) _exit(126);
        execlp("gzip", "gzip", "-dc", "--", path, (char *)NULL);
        _exit(127);
    }
    close(fd);
    if (pid < 0) return brt_fail(err, BRT_EIO, "%s: cannot start gzip: %s", path, strerror(errno));
    while (waitpid(pid, &status, 0) < 0)
        if (errno != EINTR) return brt_fail(err, BRT_EIO, "%s: waiting for gzip: %s", path, strerror(errno));
    if (WIFEXITED(status) && WEXITSTATUS(status) == 127)
        return brt_fail(err, BRT_EIO, "%s: needs the system's gzip to unpack, and gzip was not found", path);
    if (!WIFEXITED(status) || WEXITSTATUS(status) != 0)
        return brt_fail(err, BRT_EIO, "%s: gzip -dc failed (not a gzip file?)", path);
    return BRT_OK;
}

static brt_result run_ply(run *u, const shape *sh)
{
    const char *path = u->scene->files[sh->p_file];
    size_t n = strlen(path);
    char tmp[4096];
    ply_pass pp;
    brt_result r;
    pp.u = u;
    pp.sh = sh;
    tmp[0] = 0;
    if (n > 3 && strcmp(path + n - 3, ".gz") == 0) {
        r = gunzip(path, tmp, sizeof tmp, u->out.err);
        if (r == BRT_OK) r = brt_mesh_stream(tmp, ply_chunk, &pp, u->out.err);
        if (tmp[0]) unlink(tmp);   /* on every path */
        return r;
    }
    return brt_mesh_stream(path, ply_chunk, &pp, u->out.err);
}

/* Streams shapes [first, first + count) of one object (or, for
** NO_OBJECT ranges, the world shapes among them). */
static brt_result run_shapes(const ex_pbrt *scene, size_t first, size_t count, uint32_t owner,
                             brt_triangle_fn emit, void *user, brt_error *err)
{
    run u;
    size_t i;
    brt_result r = BRT_OK;
    memset(&u, 0, sizeof u);
    u.in.fd = -1;
    u.scene = scene;
    u.out.emit = emit;
    u.out.user = user;
    u.out.err = err;
    if (!(u.out.corners = malloc((size_t)CHUNK_TRIS * 9 * sizeof(float))))
        return brt_fail(err, BRT_ENOMEM, "out of memory");
    for (i = first; i < first + count && r == BRT_OK; i++) {
        const shape *sh = &scene->shapes[i];
        if (sh->object != owner) continue;
        r = sh->kind == SHAPE_PLY ? run_ply(&u, sh) : sh->kind == SHAPE_LOOP ? run_loop(&u, sh) : run_mesh(&u, sh);
    }
    if (r == BRT_OK) r = sink_flush(&u.out);
    if (r != BRT_OK && err) printable(err->message);
    if (u.in.buf) reader_close(&u.in);
    free(u.positions);
    free(u.indices);
    free(u.out.corners);
    return r;
}

/* ex_pbrt_open's last check: each loopsubdiv's control mesh is one
** pbrt-v4 can refine (examples/lib/loopsubdiv.h), so that a bad one is
** refused at its Shape's line before any stream runs.  Its indices are
** read again and held while checked. */
static brt_result check_loops(const ex_pbrt *scene, brt_error *err)
{
    run u;
    size_t i;
    brt_result r = BRT_OK;
    memset(&u, 0, sizeof u);
    u.in.fd = -1;
    u.scene = scene;
    u.out.err = err;
    for (i = 0; i < scene->shape_count && r == BRT_OK; i++) {
        const shape *sh = &scene->shapes[i];
        if (sh->kind != SHAPE_LOOP) continue;
        r = run_loop_indices(&u, sh);
        if (r == BRT_OK && (r = ex_loop_check(u.indices, (uint32_t)(sh->i_count / 3), (uint32_t)(sh->p_count / 3),
                                              err)) != BRT_OK)
            r = loop_failed(scene, sh, r, err);
    }
    if (u.in.buf) reader_close(&u.in);
    free(u.indices);
    return r;
}

static brt_result world_run(const void *user, brt_triangle_fn emit, void *emit_user, brt_error *err)
{
    const ex_pbrt *s = user;
    return run_shapes(s, 0, s->shape_count, NO_OBJECT, emit, emit_user, err);
}

static brt_result prototype_run(const void *user, uint32_t id, brt_triangle_fn emit, void *emit_user,
                                brt_error *err)
{
    const ex_pbrt *s = user;
    const object *o;
    if (id >= s->prototype_count) return brt_fail(err, BRT_EARG, "prototype %lu of %lu", (unsigned long)id,
                                                  (unsigned long)s->prototype_count);
    o = &s->objects[s->prototypes[id]];
    return run_shapes(s, o->first_shape, o->shape_count, s->prototypes[id], emit, emit_user, err);
}

static brt_result instances_run(const void *user, brt_instance_fn emit, void *emit_user, brt_error *err)
{
    const ex_pbrt *s = user;
    size_t i;
    for (i = 0; i < s->instance_count; i += CHUNK_TRIS) {
        size_t n = s->instance_count - i < CHUNK_TRIS ? s->instance_count - i : CHUNK_TRIS;
        brt_result r = emit(emit_user, s->instances + i, (uint32_t)n, (uint32_t)i, err);
        if (r != BRT_OK) return r;
    }
    return BRT_OK;
}

/* ===================================================================== */
/* Part VI: the public functions                                         */
/* ===================================================================== */

brt_result ex_pbrt_open(const char *path, ex_pbrt **out, brt_error *err)
{
    parser p;
    brt_result r;
    size_t i;
    *out = NULL;
    if (err) err->message[0] = 0;
    memset(&p, 0, sizeof p);
    p.err = err;
    p.object = NO_OBJECT;
    p.g.start_active = 1;
    xf_identity(p.g.ctm);
    if (!(p.scene = calloc(1, sizeof *p.scene))) return brt_fail(err, BRT_ENOMEM, "out of memory");
    r = parse(&p, path);
    if (r == BRT_OK) r = check_loops(p.scene, err);
    if (r != BRT_OK && err) printable(err->message);
    while (p.depth > 0) reader_close(&p.files[--p.depth]);
    for (i = 0; i < p.named_count; i++) free(p.named[i].name);
    free(p.named);
    free(p.stack);
    if (r != BRT_OK) { ex_pbrt_close(p.scene); return r; }
    *out = p.scene;
    return BRT_OK;
}

void ex_pbrt_close(ex_pbrt *scene)
{
    size_t i;
    if (!scene) return;
    for (i = 0; i < scene->file_count; i++) free(scene->files[i]);
    for (i = 0; i < scene->object_count; i++) free(scene->objects[i].name);
    free(scene->files);
    free(scene->folder);
    free(scene->shapes);
    free(scene->objects);
    free(scene->slot_of);
    free(scene->prototypes);
    free(scene->instances);
    free(scene->skipped);
    free(scene->summary);
    free(scene);
}

void ex_pbrt_source(const ex_pbrt *scene, brt_scene_source *source)
{
    memset(source, 0, sizeof *source);
    source->world.run = scene->world_shapes ? world_run : NULL;
    source->world.user = scene;
    source->prototype_count = scene->prototype_count;
    source->prototype = prototype_run;
    source->instances = instances_run;
    source->user = scene;
}

void ex_pbrt_counts(const ex_pbrt *scene, uint64_t *world_shapes, uint32_t *prototypes,
                    uint32_t *instances)
{
    if (world_shapes) *world_shapes = scene->world_shapes;
    if (prototypes) *prototypes = scene->prototype_count;
    if (instances) *instances = (uint32_t)scene->instance_count;
}

uint64_t ex_pbrt_triangles(const ex_pbrt *scene)
{
    uint64_t total = 0;
    size_t i;
    for (i = 0; i < scene->shape_count; i++) {
        const shape *sh = &scene->shapes[i];
        const char *path = scene->files[sh->p_file];
        size_t n;
        switch (sh->kind) {
        case SHAPE_TRIANGLES: total += sh->has_indices ? sh->i_count / 3 : 1; break;
        case SHAPE_BILINEAR: total += sh->has_indices ? 2 * (sh->i_count / 4) : 2; break;
        case SHAPE_LOOP: total += ex_loop_triangle_count(sh->i_count / 3, sh->levels); break;
        case SHAPE_PLY:
            n = strlen(path);
            if (!(n > 3 && strcmp(path + n - 3, ".gz") == 0)) total += ex_mesh_file_triangles(path);
            break;
        }
    }
    return total;
}

int ex_pbrt_camera(const ex_pbrt *scene, float eye[3], float target[3], float up[3],
                   float *fov_degrees, int *mirrored)
{
    if (!scene->has_camera) return 0;
    memcpy(eye, scene->eye, sizeof scene->eye);
    memcpy(target, scene->target, sizeof scene->target);
    memcpy(up, scene->up, sizeof scene->up);
    *fov_degrees = scene->fov;
    if (mirrored) *mirrored = scene->mirrored;
    return 1;
}

int ex_pbrt_film(const ex_pbrt *scene, uint32_t *width, uint32_t *height)
{
    *width = scene->has_film ? scene->film_width : 1280;   /* pbrt-v4's defaults */
    *height = scene->has_film ? scene->film_height : 720;
    return scene->has_film;
}

/* pbrt-v4's PerspectiveCamera: raster (x right, y down, over the image)
** maps linearly onto the screen window, screen (x, y) is the camera-space
** direction (x tan(fov/2), y tan(fov/2), 1) (Perspective's divide by z
** and scale by 1/tan(fov/2), undone), and world-from-camera carries it
** out.  Written as forward + X right + Y up for X = 2 sx - 1 and
** Y = 1 - 2 sy, every term is linear in (sx, sy), so the three vectors
** are the camera-space ones put through world-from-camera's linear part. */
int ex_pbrt_camera_frame(const ex_pbrt *scene, uint32_t width, uint32_t height, double eye[3],
                         double forward[3], double right[3], double up[3])
{
    const double *m = scene->world_from_camera;
    double sw[4], t, frame, f[3], r[3], u[3];
    int k;
    if (!scene->has_camera || width == 0 || height == 0) return 0;
    frame = scene->frame > 0 ? scene->frame : (double)width / (double)height;
    if (scene->has_screen) memcpy(sw, scene->screen, sizeof sw);
    else if (frame > 1) { sw[0] = -frame; sw[1] = frame; sw[2] = -1; sw[3] = 1; }   /* fov spans y */
    else { sw[0] = -1; sw[1] = 1; sw[2] = -1 / frame; sw[3] = 1 / frame; }           /* fov spans x */
    t = tan(scene->fov * (PI / 360));
    f[0] = t * 0.5 * (sw[0] + sw[1]); f[1] = t * 0.5 * (sw[2] + sw[3]); f[2] = 1;
    r[0] = t * 0.5 * (sw[1] - sw[0]); r[1] = 0; r[2] = 0;
    u[0] = 0; u[1] = t * 0.5 * (sw[3] - sw[2]); u[2] = 0;
    for (k = 0; k < 3; k++) {
        eye[k] = m[4 * k + 3];
        forward[k] = m[4 * k] * f[0] + m[4 * k + 1] * f[1] + m[4 * k + 2] * f[2];
        right[k] = m[4 * k] * r[0];
        up[k] = m[4 * k + 1] * u[1];
    }
    return 1;
}

const char *ex_pbrt_skipped(const ex_pbrt *scene)
{
    return scene->summary ? scene->summary : "";
}
