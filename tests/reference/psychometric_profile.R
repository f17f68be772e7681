# Reference values for facelab.analysis.bayes_psychometric.posterior_fit(interval="profile"):
# the posterior mode and 95 % profile intervals of P = 1/2 + (1/2 - lambda) * F(level), F
# logistic with midpoint m and width w (5 % -> 95 %), under psignifit's default priors, found
# here by continuous optimisation (optim, uniroot) rather than facelab's grid.
# Run from this folder:  Rscript psychometric_profile.R > psychometric_profile_R.json
# Needs Debian r-base-core only.
d <- read.csv("psychometric_profile.csv")
gamma <- 0.5
ln19 <- log(19)
drop <- qchisq(0.95, df = 1) / 2

cosine_window <- function(x, zero_lo, flat_lo, flat_hi, zero_hi) {
  ifelse(x <= zero_lo | x >= zero_hi, 0,
    ifelse(x < flat_lo, 0.5 - 0.5 * cos(pi * (x - zero_lo) / (flat_lo - zero_lo)),
      ifelse(x > flat_hi, 0.5 + 0.5 * cos(pi * (x - flat_hi) / (zero_hi - flat_hi)), 1)))
}

one <- function(s) {
  x <- s$level; k <- s$k; n <- s$n
  lo <- min(x); hi <- max(x); span <- hi - lo; step <- min(diff(sort(unique(x))))
  # log posterior in (m, log w, lambda); the width prior is a density in w, times w for log w
  lpost <- function(m, lw, lam) {
    w <- exp(lw)
    pm <- cosine_window(m, lo - 0.5 * span, lo, hi, hi + 0.5 * span)
    pw <- cosine_window(w, step, 2 * step, span, 3 * span) * w
    if (pm <= 0 || pw <= 0 || lam < 0 || lam > 0.5) return(-1e10)
    p <- gamma + (1 - gamma - lam) * plogis(2 * ln19 / w * (x - m))
    p <- pmin(pmax(p, 1e-12), 1 - 1e-12)  # as facelab clips
    sum(dbinom(k, n, p, log = TRUE) - lchoose(n, k)) + log(pm) + log(pw) + dbeta(lam, 1, 10, log = TRUE) - log(10)
  }
  box <- list(m = c(lo - 0.5 * span, hi + 0.5 * span), lw = log(c(step, 3 * span)), lam = c(0, 0.5))
  best_of <- function(f, starts, lower, upper) {
    fits <- lapply(starts, function(p0) optim(p0, function(p) -f(p), method = "L-BFGS-B",
                                               lower = lower, upper = upper))
    fits[[which.min(sapply(fits, `[[`, "value"))]]
  }
  grid_starts <- function(...) {
    g <- expand.grid(...)
    lapply(seq_len(nrow(g)), function(i) unlist(g[i, ]))
  }
  eps <- 1e-6
  ms <- seq(lo, hi, length.out = 5); lws <- log(seq(2 * step, span, length.out = 4)); lams <- c(0.01, 0.05)
  mode <- best_of(function(p) lpost(p[1], p[2], p[3]), grid_starts(ms, lws, lams),
                  c(box$m[1] + eps, box$lw[1] + eps, 0), c(box$m[2] - eps, box$lw[2] - eps, 0.5))
  top <- -mode$value
  prof_m <- function(m) -best_of(function(p) lpost(m, p[1], p[2]), grid_starts(lws, lams),
                                 c(box$lw[1] + eps, 0), c(box$lw[2] - eps, 0.5))$value
  prof_lw <- function(lw) -best_of(function(p) lpost(p[1], lw, p[2]), grid_starts(ms, lams),
                                   c(box$m[1] + eps, 0), c(box$m[2] - eps, 0.5))$value
  ends <- function(prof, at, limits) {
    f <- function(v) top - prof(v) - drop
    c(uniroot(f, c(limits[1] + eps, at))$root, uniroot(f, c(at, limits[2] - eps))$root)
  }
  m_iv <- ends(prof_m, mode$par[1], box$m)
  lw_iv <- ends(prof_lw, mode$par[2], box$lw)
  fmt <- function(v) formatC(v, digits = 8, format = "g")
  sprintf('{"midpoint": %s, "midpoint_ci": [%s, %s], "width": %s, "width_ci": [%s, %s], "lapse": %s}',
          fmt(mode$par[1]), fmt(m_iv[1]), fmt(m_iv[2]), fmt(exp(mode$par[2])),
          fmt(exp(lw_iv[1])), fmt(exp(lw_iv[2])), fmt(mode$par[3]))
}
names <- unique(d$dataset)
out <- sapply(names, function(nm) sprintf('  "%s": %s', nm, one(d[d$dataset == nm, ])))
cat("{\n", paste(out, collapse = ",\n"), "\n}\n", sep = "")
