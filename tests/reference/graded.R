# Reference values for facelab.analysis.graded, computed with R (afex + emmeans, lme4).
# Run from this folder:  Rscript graded.R > graded_R.json
# Needs Debian r-base-core, r-cran-afex, r-cran-emmeans, r-cran-lme4, r-cran-lmertest.
suppressPackageStartupMessages({library(afex); library(emmeans); library(lme4); library(lmerTest)})
d <- read.csv("graded.csv")
d$participant <- factor(d$participant)
d$lev <- factor(d$level)

# the linear trend contrast of the RM ANOVA on participant means, with its own error term
a <- aov_ez("participant", "rating", d, within = "lev", fun_aggregate = mean)
x <- sort(unique(d$level))
w <- (x - mean(x)) / sum((x - mean(x))^2)  # weights giving the least-squares slope
ct <- summary(contrast(emmeans(a, ~lev, model = "multivariate"), list(linear = w)))

# the mixed model with random intercepts and slopes per participant, REML
m <- lmerTest::lmer(rating ~ level + (1 + level | participant), data = d, REML = TRUE)
fe <- summary(m, ddf = "Satterthwaite")$coefficients
vc <- as.data.frame(VarCorr(m))

fmt <- function(v) formatC(v, digits = 12, format = "g")
cat("{\n")
cat(sprintf('  "trend": {"slope": %s, "se": %s, "t": %s, "df": %s, "p": %s},\n',
            fmt(ct$estimate), fmt(ct$SE), fmt(ct$t.ratio), fmt(ct$df), fmt(ct$p.value)))
cat(sprintf(paste0('  "lmm": {"intercept": %s, "slope": %s, "slope_se": %s, ',
                   '"slope_df": %s, "slope_p": %s, ',
                   '"sd_intercept": %s, "sd_slope": %s, "corr": %s, "sd_residual": %s}\n'),
            fmt(fe[1, 1]), fmt(fe[2, 1]), fmt(fe[2, 2]), fmt(fe[2, "df"]), fmt(fe[2, "Pr(>|t|)"]),
            fmt(vc$sdcor[1]), fmt(vc$sdcor[2]), fmt(vc$sdcor[3]), fmt(vc$sdcor[4])))
cat("}\n")
