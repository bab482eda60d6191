"""The shared model every estimator reads: the IMU stream cut into steps at keyframe and measurement
times (:mod:`~smoother.model.timeline`), an estimate's states between its keyframes
(:mod:`~smoother.model.between`), the problem built from a dataset -- keyframes, IMU and
measurement factors, priors, initial values (:mod:`~smoother.model.problem`) -- the vectorised
factor blocks with their linearisation (:mod:`~smoother.model.blocks`), and the marginal and joint
covariances of the variables (:mod:`~smoother.model.covariances`)."""
