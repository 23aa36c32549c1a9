"""The body: skeleton (ASF/AMC, URDF), forward kinematics, joint limits, rotations, the pose prior and keypoint
sets. Imports only the leaf utilities (errors, checks, package_data)."""
