/* The tracker's per-frame hot path in C (host/flytrack_host/tracking/kernel.py loads it with
 * ctypes).
 *
 * One call does, for all targets and cameras of a frame, what tracker.py does with NumPy: gather
 * the frame's finite points from the raw protocol bytes, predict (constant velocity, Braid's Q),
 * project every target through every camera with OpenCV distortion and its 2x3 Jacobian, gate and
 * score every (point, target) pair (image gate, area gate, Mahalanobis distance to the camera ray),
 * pick each camera's nearest neighbour per target, then the Joseph-form EKF update, the running
 * area, the body orientation, the death test and the birth prefilter on the unclaimed points. The
 * caller owns every buffer (no allocation here); the rare decisions that need scipy (clashes over a
 * point, flydra's merge-prevention rule) stop the call half way so that Python settles them and
 * then calls ftk_update.
 */
#ifndef FLYTRACK_TRACKER_KERNEL_H
#define FLYTRACK_TRACKER_KERNEL_H

#include <stddef.h>
#include <stdint.h>

#define FTK_ABI_VERSION 3

/* A protocol point is 11 little-endian 4-byte words (protocol/SPEC.md); the ones read here. */
#define FTK_POINT_WORDS 11

/* Packed camera table: FTK_CAM_STRIDE doubles per camera slot, at these offsets. */
enum {
    FTK_CAM_R = 0,       /* 3x3 world -> camera rotation, row-major */
    FTK_CAM_T = 9,       /* translation (3) */
    FTK_CAM_K = 12,      /* fx, skew, cx, fy, cy of the distortion's K (Camera.Kd) */
    FTK_CAM_DIST = 17,   /* k1, k2, p1, p2, k3 (OpenCV) */
    FTK_CAM_CENTER = 22, /* camera centre in the world (3) */
    FTK_CAM_RAYB = 25,   /* 3x3 R^T K^-1: world ray direction of an undistorted pixel */
    FTK_CAM_P = 34,      /* 3x4 undistorted-pixel projection matrix */
    FTK_CAM_DFA = 46,    /* distortion frame q = A q0 + b: a00 a01 a10 a11 b0 b1 (OpenCV: I, 0) */
    FTK_CAM_STRIDE = 52
};

typedef struct {
    double gate_px;
    double area_gate_ratio;
    double min_area_px;
    double max_mahalanobis;
    double r2; /* measurement variance, px^2 */
    double motion_noise_scale;
    double death_var;
    double area_smoothing;
    double min_eccentricity;
    double min_plane_tan_half; /* tan(orientation_min_plane_angle / 2) */
    double birth_seed_gate_px; /* a pair whose Sampson distance is under this may give a birth */
    int64_t exclusive_points;
    int64_t birth_min_cameras;
} ftk_params;

/* Caller-owned buffers. n_cap points and t_cap targets are the capacities; arrays indexed by
 * (camera, target) or (point, target) use the current target count T as the inner stride. */
typedef struct {
    int64_t n_cameras;
    int64_t t_cap;
    int64_t n_cap;
    int64_t scratch_len;
    /* targets (t_cap rows): state (6), covariance (36), running area, frames with observations,
     * body axis (3, NaN when unknown) */
    double *x;
    double *P;
    double *area;
    int64_t *n_obs;
    double *axis;
    /* points (n_cap rows) in camera-slot order */
    int64_t *slot;
    int64_t *index;  /* position in its camera's detection array */
    int64_t *rank;   /* position among its camera's finite points */
    int64_t *starts; /* n_cameras + 1 */
    double *uv;      /* distorted (u, v) */
    double *uvi;     /* undistorted (u, v) */
    double *parea;
    double *ori; /* NaN when unknown */
    double *ecc;
    double *rays; /* (3) world ray directions, not normalised */
    uint8_t *ori_ok;
    uint8_t *claimed;
    /* (point, target) */
    double *cost; /* Mahalanobis distance to the ray, inf where a gate refuses */
    double *d2;   /* squared image distance to the predicted projection */
    /* (camera, target) */
    double *puv;     /* (2) predicted distorted pixel */
    double *J;       /* (2x3) Jacobian of the distorted projection */
    uint8_t *front;  /* target in front of the camera */
    int64_t *assign; /* chosen point row or -1 */
    /* (target) */
    int64_t *n_cams;
    uint8_t *dead;
    double *scratch; /* scratch_len doubles, see ftk_scratch_len */
} ftk_buffers;

/* Figures a call writes into its int64 stats array. */
enum {
    FTK_ST_POINTS = 0,     /* finite points gathered */
    FTK_ST_NONFINITE,      /* points skipped: NaN/inf position or area */
    FTK_ST_NONFINITE_ORI,  /* points with an infinite angle or eccentricity (used without angle) */
    FTK_ST_MAX_PER_CAMERA, /* most finite points of one camera */
    FTK_ST_CONFLICTS,      /* cameras where targets' nearest neighbours clash */
    FTK_ST_RESOLVE,        /* 1: the caller must settle the association, then call ftk_update */
    FTK_ST_UPDATED,        /* targets updated (accepted) */
    FTK_ST_REJECTED,       /* updates refused (posterior not finite / not positive definite) */
    FTK_ST_DEAD,           /* targets whose position std passed the death threshold */
    FTK_ST_UNCLAIMED,      /* points no target claimed */
    FTK_ST_BIRTH_PAIRS,    /* 1 when some unclaimed pair passes the birth prefilter */
    FTK_ST_COUNT
};

enum { FTK_OK = 0, FTK_EINVAL = -1, FTK_ECAPACITY = -2 };

int ftk_abi_version(void);
size_t ftk_sizeof_params(void);
size_t ftk_sizeof_buffers(void);
/* Doubles of scratch the calls need for this many cameras and target capacity. */
int64_t ftk_scratch_len(int64_t n_cameras, int64_t t_cap);

/* Gather, predict (when n_targets > 0), project and associate. counts[c]: points of camera slot c
 * in raw (the cameras' protocol bytes joined in slot order). stats: FTK_ST_COUNT int64s. */
int ftk_associate(const ftk_params *p, const double *cams, const ftk_buffers *b, const void *raw,
                  const int64_t *counts, int64_t n_targets, double dt, int64_t *stats);

/* EKF update with b->assign, area, orientation, deaths, unclaimed points and the birth prefilter.
 */
int ftk_update(const ftk_params *p, const double *cams, const ftk_buffers *b, int64_t n_targets,
               int64_t *stats);

/* ftk_associate, then ftk_update unless stats[FTK_ST_RESOLVE] asks the caller to settle first. */
int ftk_frame(const ftk_params *p, const double *cams, const ftk_buffers *b, const void *raw,
              const int64_t *counts, int64_t n_targets, double dt, int64_t *stats);

#endif
