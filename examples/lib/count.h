/*
** count.h -- a mesh file's triangles counted before it is read (count.c).
*/
#ifndef EX_COUNT_H
#define EX_COUNT_H

#include <stdint.h>

/* The triangles of a mesh file before it is read (for the default point
** size, ex_default_point_tris): an OBJ's faces counted in one scan of its
** bytes, a polygon of n corners n - 2 triangles, as brt_mesh_load fans it
** (no number is parsed: a fraction of the read's time, on every run);
** a PLY's header alone, its face count, exact when the faces are
** triangles and a lower bound when some have more corners (their lists are
** not read).  0 when the file cannot be read (the build reports why). */
uint64_t ex_mesh_file_triangles(const char *path);

#endif
