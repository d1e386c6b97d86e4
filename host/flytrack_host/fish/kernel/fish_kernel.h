/* The hot loop of the fish shape fit (host/flytrack_host/fish/fit.py, seed 004 eq. 4.2): the
 * distance of each back-projected contour line to a sampled model surface, for a batch of candidate
 * states. Loaded with ctypes by host/flytrack_host/fish/kernel.py; NumPy computes the same in
 * fit.py. */
#ifndef FISH_KERNEL_H
#define FISH_KERNEL_H
#include <stdint.h>

#define FFK_ABI_VERSION 1

int ffk_abi_version(void);

/* S: surface points (B, Ns, Nu, 3) row-major; p: line feet (N, 3) (the point of each line nearest
 * the origin, so p.v = 0); v: unit directions (N, 3). D (B, N) receives, for each state and line,
 * the least distance from the line to the surface: the squared distance to each point, refined by a
 * parabola through the least sample and its neighbours around each ellipse (cyclic in u), then
 * along s; sqrt at the end. Stations whose bounding sphere is farther than the best distance found
 * are skipped. Returns 0, or -1 for bad sizes. Non-finite inputs give non-finite outputs, never a
 * crash. */
int ffk_line_distances(const double *S, int64_t B, int64_t Ns, int64_t Nu, const double *p,
                       const double *v, int64_t N, double *D);

#endif
