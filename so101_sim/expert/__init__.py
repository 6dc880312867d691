"""The scripted expert: solves every task of the suite from the true object poses.

``ScriptedExpert(task).select_action(obs)`` plans top-down grasps with MuJoCo-Jacobian IK
(``kinematics.TopDownIK``) and follows smooth joint-space segments; the task's kind says
where each cube goes. It is the demonstrator behind ``so101-sim record``.
"""

from so101_sim.expert.kinematics import TopDownIK
from so101_sim.expert.scripted import ScriptedExpert

__all__ = ["ScriptedExpert", "TopDownIK"]
